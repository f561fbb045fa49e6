"""Inference protocols (docs/definitions.md §13): sliding windows against a brute-force loop over
windows, test-time augmentation against a loop over views, both stated in evaluate.py's and
predict.py's outputs, and bad values refused in one line before the network loads."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image
from torch import nn
from torch.nn import functional as F

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main, predict_main
from costseg.data.from_config import build_dataset
from costseg.networks import ImageNetwork, load_costseg_checkpoint
from costseg.networks.mc_dropout import mc_dropout_probs
from costseg.networks.sliding import SlidingWindow, window_starts
from costseg.networks.tta import TestTimeAugmentation


def _context_net(seed: int = 0) -> ImageNetwork:
    """Logits at half resolution from 3 x 3 convolutions: every window border shows."""
    torch.manual_seed(seed)
    net = nn.Sequential(
        nn.Conv2d(3, 6, 3, padding=1), nn.ReLU(), nn.Conv2d(6, 5, 3, stride=2, padding=1)
    )
    return ImageNetwork(net)


def _images(b: int, h: int, w: int, seed: int = 1) -> torch.Tensor:
    return torch.randint(0, 256, (b, 3, h, w), generator=torch.Generator().manual_seed(seed)).byte()


def _starts(size: int, crop: int, stride: int) -> list[int]:
    """Every stride while a window still ends inside, then one window ending on the border."""
    length = min(crop, size)
    return [*range(0, size - length, stride), size - length]


def _brute_force_slide(net, images, crop, stride) -> torch.Tensor:
    """One forward per window; per pixel the sum of the covering windows' logits and their count."""
    b, _, height, width = images.shape
    h, w = min(crop[0], height), min(crop[1], width)
    total, count = torch.zeros(b, 5, height, width), torch.zeros(height, width)
    for y in _starts(height, crop[0], stride[0]):
        for x in _starts(width, crop[1], stride[1]):
            total[:, :, y : y + h, x : x + w] += net(images[:, :, y : y + h, x : x + w])
            count[y : y + h, x : x + w] += 1
    assert count.min() >= 1
    return total / count


def test_the_grid_is_mmsegmentations():
    # Cityscapes in mmsegmentation: crop 769 x 769, stride 513 on 1024 x 2048 images
    assert window_starts(1024, 769, 513) == [0, 255]
    assert window_starts(2048, 769, 513) == [0, 513, 1026, 1279]
    for size, crop, stride in [(20, 8, 5), (27, 10, 7), (16, 8, 8), (7, 9, 3), (9, 9, 1)]:
        assert window_starts(size, crop, stride) == _starts(size, crop, stride)


def test_a_crop_as_large_as_the_image_is_the_whole_image_forward(one_thread):
    net, images = _context_net(), _images(2, 18, 26)
    with torch.inference_mode():
        whole = net(images)
        for crop in [(18, 26), (32, 40), (18, 64)]:
            assert torch.equal(SlidingWindow(net, crop, (5, 7))(images), whole)


@pytest.mark.parametrize(
    ("size", "crop", "stride", "per_forward"),
    [
        ((20, 27), (8, 10), (5, 7), 8),  # overlapping windows, several per forward
        ((20, 27), (8, 10), (8, 10), 1),  # tiled, one window per forward, the last overlaps
        ((12, 40), (16, 16), (8, 12), 3),  # image shorter than the crop: full-height windows
    ],
)
def test_windows_equal_a_brute_force_loop(size, crop, stride, per_forward, one_thread):
    net, images = _context_net(), _images(2, *size)
    with torch.inference_mode():
        got = SlidingWindow(net, crop, stride, crops_per_forward=per_forward)(images)
        expected = _brute_force_slide(net, images, crop, stride)
        assert not torch.allclose(got, net(images), atol=1e-3)  # the windows show
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)


def test_flip_of_a_flip_equivariant_network_is_the_plain_one(one_thread):
    torch.manual_seed(0)
    pointwise = ImageNetwork(nn.Sequential(nn.Conv2d(3, 8, 1), nn.ReLU(), nn.Conv2d(8, 5, 1)))
    symmetric = nn.Conv2d(3, 5, 3, padding=1)
    with torch.no_grad():
        symmetric.weight.copy_((symmetric.weight + symmetric.weight.flip(-1)) / 2)
    images = _images(2, 10, 13)
    with torch.inference_mode():
        plain = pointwise(images).softmax(1)
        assert torch.equal(TestTimeAugmentation(pointwise, flip=True)(images), plain)
        mirrored = ImageNetwork(symmetric)
        got = TestTimeAugmentation(mirrored, flip=True)(images)
        torch.testing.assert_close(got, mirrored(images).softmax(1), rtol=1e-6, atol=1e-6)
        # a network that is not flip-equivariant changes
        other = _context_net()
        assert not torch.allclose(TestTimeAugmentation(other, True)(images), other(images))


def test_scales_and_flips_equal_a_loop_over_views(one_thread):
    net, images = _context_net(), _images(2, 15, 22)
    scales = (0.5, 1.0, 1.3)
    expected = torch.zeros(2, 5, 15, 22)
    with torch.inference_mode():
        for s in scales:
            size = (int(15 * s + 0.5), int(22 * s + 0.5))
            x = F.interpolate(images.float(), size=size, mode="bilinear", align_corners=False)
            x = x.round().clamp(0, 255).byte()
            for flip in (False, True):
                logits = net(x.flip(3)).flip(3) if flip else net(x)
                logits = F.interpolate(logits, size=(15, 22), mode="bilinear", align_corners=False)
                expected += logits.softmax(1) / 6
        got = TestTimeAugmentation(net, flip=True, scales=scales)(images)
    torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-6)


def test_windows_run_inside_each_view_and_dropout_passes_inside_each_view(one_thread):
    torch.manual_seed(0)
    net = ImageNetwork(nn.Sequential(nn.Conv2d(3, 5, 3, padding=1), nn.Dropout(0.5)))
    images = _images(1, 12, 16)
    slide = SlidingWindow(net, (8, 8), (4, 6))
    with torch.inference_mode():
        tta = TestTimeAugmentation(slide, flip=True, scales=(1.0, 0.75))
        expected = sum(
            F.interpolate(
                slide(x.flip(3)).flip(3) if flip else slide(x),
                size=(12, 16),
                mode="bilinear",
                align_corners=False,
            ).softmax(1)
            for x in (images, _resized(images, (9, 12)))
            for flip in (False, True)
        )
        torch.testing.assert_close(tta(images), expected / 4, rtol=1e-6, atol=1e-6)
        mc = TestTimeAugmentation(slide, flip=True, passes=3, seed=7)
        got = mc(images, ["a"])
        assert torch.equal(got, mc(images, ["a"]))  # seeded
        plain_view = mc_dropout_probs(slide, images, 3, 7, "a")  # the image as it is: key "a"
        flipped = mc_dropout_probs(_Flipped(slide), images, 3, 7, "a flip")
        torch.testing.assert_close(got, (plain_view + flipped) / 2, rtol=1e-6, atol=1e-6)
        assert not net.training and not any(m.training for m in net.modules())


class _Flipped(nn.Module):
    def __init__(self, network: nn.Module) -> None:
        super().__init__()
        self.network = network

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.network(images.flip(3)).flip(3)


def _resized(images: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    x = F.interpolate(images.float(), size=size, mode="bilinear", align_corners=False)
    return x.round().clamp(0, 255).byte()


PROTOCOL = ["--inference", "slide", "--crop", "40", "48", "--stride", "24", "40", "--tta", "flip"]


def _reference(network, image: torch.Tensor) -> torch.Tensor:
    slide = SlidingWindow(network, (40, 48), (24, 40))
    with torch.inference_mode():
        return TestTimeAugmentation(slide, flip=True)(image[None])[0]


def test_evaluate_runs_and_states_the_protocol(tiny_run, tmp_path):
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    out = tmp_path / "eval"
    evaluate_main(["--ckpt_path", str(ckpt), "--cost", "robotistic", "--output_dir", str(out),
                   "--limit", "1", "--num_examples", "0", "--no-progress", "--save-probs",
                   *PROTOCOL])  # fmt: skip
    results = json.loads((out / "results.json").read_text())
    assert results["source"]["inference"] == "slide crop 40x48 stride 24x40"
    assert results["source"]["tta"] == "flip"
    assert "mean softmax of 2 views (the image, flip)" in results["probabilities"]
    assert "sliding windows (slide crop 40x48 stride 24x40)" in results["probabilities"]
    assert "2 views" in (out / "table.md").read_text()
    checkpoint = load_costseg_checkpoint(ckpt)
    dataset = build_dataset(checkpoint.data_config, "val")
    saved = torch.from_numpy(np.load(out / "probs" / "val_000000.npz")["probs"]).float()
    expected = _reference(checkpoint.network, dataset[0][0])
    torch.testing.assert_close(saved, expected, atol=1e-3, rtol=0)


def test_predict_runs_and_states_the_protocol(tiny_run, tmp_path):
    ckpt = find_checkpoint(None, runs_dir=tiny_run[2])
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (50, 70, 3), dtype=np.uint8)
    Image.fromarray(image).save(tmp_path / "photo.png")
    out = tmp_path / "out"
    predict_main(["--input", str(tmp_path / "photo.png"), "--ckpt_path", str(ckpt), "--cost",
                  "egoistic", "--output_dir", str(out), "--save-probs", "--no-progress",
                  "--explorer", "--num_examples", "1", *PROTOCOL])  # fmt: skip
    source = json.loads((out / "counts.json").read_text())["source"]
    assert source["inference"] == "slide crop 40x48 stride 24x40" and source["tta"] == "flip"
    page = (out / "explorer.html").read_text()
    assert "inference: slide crop 40x48 stride 24x40; test-time augmentation: flip" in page
    saved = torch.from_numpy(np.load(out / "probs" / "photo.npz")["probs"]).float()
    network = load_costseg_checkpoint(ckpt).network
    expected = _reference(network, torch.from_numpy(image).permute(2, 0, 1))
    torch.testing.assert_close(saved, expected, atol=1e-3, rtol=0)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--inference", "slide"], "needs --crop H W and --stride H W"),
        (["--crop", "8", "8", "--stride", "8", "8"], "go with --inference slide"),
        (["--inference", "slide", "--crop", "8", "8", "--stride", "9", "4"], "exceeds --crop"),
        (["--inference", "slide", "--crop", "0", "8", "--stride", "1", "1"], "whole number >= 1"),
        (["--inference", "slide", "--crop", "8"], "expected 2 arguments"),
        (["--inference", "tiles"], "invalid choice"),
        (["--tta", "rotate"], "invalid choice"),
        (["--scales", "0"], "a number > 0"),
        (["--scales", "1", "0.5", "1"], "repeats a scale"),
    ],
)
def test_bad_values_are_one_line_before_the_network_loads(args, message, tmp_path, capsys):
    image = tmp_path / "photo.png"
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(image)
    missing = str(tmp_path / "none.ckpt")  # never opened: the protocol is checked first
    for main, extra in ((evaluate_main, []), (predict_main, ["--input", str(image)])):
        with pytest.raises(SystemExit) as exit_info:
            main(["--ckpt_path", missing, *extra, *args])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err


def test_saved_probabilities_cannot_run_a_protocol(tmp_path, capsys):
    for args in (
        ["--tta", "flip"],
        ["--inference", "slide", "--crop", "4", "4", "--stride", "4", "4"],
    ):
        with pytest.raises(SystemExit) as exit_info:
            evaluate_main(["--probs", str(tmp_path), "--data_root", str(tmp_path), *args])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "saved probabilities cannot be rerun" in err
