"""Pixel-wise priors against hand loops and scipy's Gaussian filter, RoI maps, resizing, the
priors file and its cache."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from costseg.classes import CLASS_NAMES, ROI_NAMES, class_index
from costseg.data.prior_maps import PriorMaps
from costseg.data.priors import (
    check_priors_file,
    default_sigma,
    note_priors,
    pixel_priors,
    priors_note,
    read_priors_file,
    resize_priors,
    roi_map,
    save_priors,
)
from costseg.data.priors_cache import cached_priors
from costseg.data.toy import StreetScenes


def _brute_force(labels: list[torch.Tensor], n: int, eps: float) -> torch.Tensor:
    """docs/definitions.md §3 with plain loops (no smoothing)."""
    h, w = labels[0].shape
    out = torch.zeros(n, h, w, dtype=torch.float64)
    for y in range(h):
        for x in range(w):
            values = [int(label[y, x]) for label in labels if int(label[y, x]) != 255]
            freq = [values.count(c) / len(values) if values else 1 / n for c in range(n)]
            floored = [max(f, eps) for f in freq]
            for c in range(n):
                out[c, y, x] = floored[c] / sum(floored)
    return out


def _random_labels(count: int, size: tuple[int, int], n: int, seed: int) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    labels = [torch.randint(0, n, size, generator=g) for _ in range(count)]
    for label in labels:
        label[torch.rand(size, generator=g) < 0.3] = 255
    labels[0][0, 0] = labels[1][0, 0] = labels[2][0, 0] = 255  # never labelled → uniform
    return labels


def test_matches_brute_force_count() -> None:
    labels = _random_labels(count=3, size=(4, 5), n=3, seed=0)
    pi = pixel_priors(labels, num_classes=3, sigma=0, eps=1e-3, progress=False)
    assert pi.dtype == torch.float32 and pi.shape == (3, 4, 5)
    torch.testing.assert_close(pi.double(), _brute_force(labels, 3, 1e-3), atol=1e-6, rtol=0)
    torch.testing.assert_close(pi[:, 0, 0], torch.full((3,), 1 / 3))
    torch.testing.assert_close(pi.sum(dim=0), torch.ones(4, 5))


def test_ignored_pixels_count_nowhere() -> None:
    # Location (0, 0): class 1 twice, ignored three times → all mass on class 1 before the floor.
    labels = [torch.tensor([[v, 0]]) for v in (1, 255, 1, 255, 255)]
    pi = pixel_priors(labels, num_classes=2, sigma=0, eps=1e-5, progress=False)
    torch.testing.assert_close(pi[:, 0, 0], torch.tensor([1e-5, 1.0]) / (1 + 1e-5))
    torch.testing.assert_close(pi[:, 0, 1], torch.tensor([1.0, 1e-5]) / (1 + 1e-5))


def test_eps_floor_and_iterables() -> None:
    labels = _random_labels(count=12, size=(6, 7), n=19, seed=1)
    eps = 1e-4
    pi = pixel_priors(iter(labels), sigma=0, eps=eps, progress=True)  # an iterator has no len
    torch.testing.assert_close(pi.sum(dim=0), torch.ones(6, 7))
    assert pi.min() >= eps / (1 + 19 * eps) - 1e-9
    torch.testing.assert_close(pi.double(), _brute_force(labels, 19, eps), atol=1e-6, rtol=0)
    uint8 = [label.to(torch.uint8) for label in labels]
    uint8 = pixel_priors(uint8, sigma=0, eps=eps, progress=False)
    assert torch.equal(uint8, pi)


def test_smoothing_keeps_distributions() -> None:
    labels = _random_labels(count=6, size=(12, 16), n=4, seed=2)
    raw = pixel_priors(labels, num_classes=4, sigma=0, progress=False)
    smooth = pixel_priors(labels, num_classes=4, sigma=2.0, progress=False)
    torch.testing.assert_close(smooth.sum(dim=0), torch.ones(12, 16))
    assert smooth.std(dim=(1, 2)).max() < raw.std(dim=(1, 2)).min()  # spatially smoother
    torch.testing.assert_close(smooth.mean(dim=(1, 2)), raw.mean(dim=(1, 2)), atol=0.02, rtol=0)
    constant = pixel_priors([torch.full((5, 6), 2)] * 3, num_classes=4, sigma=3.0, progress=False)
    unsmoothed = pixel_priors([torch.full((5, 6), 2)], 4, sigma=0, progress=False)
    torch.testing.assert_close(constant, unsmoothed)


def test_resize_renormalises() -> None:
    pi = pixel_priors(_random_labels(4, (8, 10), 5, seed=3), num_classes=5, sigma=0, progress=False)
    for size in [(4, 5), (16, 20), (7, 13)]:
        out = resize_priors(pi, size)
        assert out.shape == (5, *size)
        torch.testing.assert_close(out.sum(dim=0), torch.ones(size))
        assert out.min() > 0
    assert torch.equal(resize_priors(pi, (8, 10)), pi)
    unnormalised = torch.rand(3, 6, 6) + 0.1
    torch.testing.assert_close(resize_priors(unnormalised, (3, 3)).sum(dim=0), torch.ones(3, 3))


def test_bad_labels_are_rejected() -> None:
    with pytest.raises(ValueError, match=r"label 1 is \(3, 4\), label 0 is \(4, 4\)"):
        pixel_priors([torch.zeros(4, 4, dtype=torch.long), torch.zeros(3, 4, dtype=torch.long)])
    with pytest.raises(ValueError, match=r"label 0 holds values \[-1, 19\]"):
        pixel_priors([torch.tensor([[0, 19, -1, 255]])])
    with pytest.raises(ValueError, match="at least one"):
        pixel_priors([])
    with pytest.raises(ValueError, match="integer"):
        pixel_priors([torch.zeros(4, 4)])
    with pytest.raises(ValueError, match="eps"):
        pixel_priors([torch.zeros(4, 4, dtype=torch.long)], num_classes=19, eps=0.1)


def test_roi_map_on_hand_made_priors() -> None:
    pi = torch.full((19, 2, 3), 0.01)
    road, sidewalk = class_index("road"), class_index("sidewalk")
    building, sky, person = class_index("building"), class_index("sky"), class_index("person")
    pi[road, 0, 0] = 0.5
    pi[sidewalk, 0, 1] = 0.3
    pi[building, 0, 2] = 0.2
    pi[sky, 1, 0] = 0.4
    pi[person, 1, 1], pi[building, 1, 1] = 0.9, 0.05  # person is no RoI class
    pi[road, 1, 2] = pi[sky, 1, 2] = 0.3  # tie → lower RoI id
    roi = roi_map(pi)
    assert roi.dtype == torch.int64
    assert roi.tolist() == [[1, 2, 3], [4, 3, 1]]
    assert [ROI_NAMES[i] for i in roi[0].tolist()] == ["street", "sidewalk", "building"]
    with pytest.raises(ValueError, match="19 classes"):
        roi_map(torch.zeros(5, 2, 2))


def test_roi_map_on_toy_priors() -> None:
    scenes = StreetScenes(split="train", length=100, size=(64, 128), seed=0)
    # Unsmoothed counts: with the default σ = 5 px the thinner left sidewalk loses to road.
    roi = roi_map(pixel_priors((label for _, label in scenes), sigma=0, progress=False))
    h, w = roi.shape
    street, sidewalk, building, sky = 1, 2, 3, 4
    assert roi[h - 4 :, w // 2 - 8 : w // 2 + 8].eq(street).all()
    assert roi[:4, w // 2 - 4 : w // 2 + 4].eq(sky).all()
    assert roi[:, : w // 2].eq(sidewalk).any() and roi[:, w // 2 :].eq(sidewalk).any()
    assert roi[h // 4, :8].eq(building).all() and roi[h // 4, -8:].eq(building).all()
    assert set(roi.unique().tolist()) == {street, sidewalk, building, sky}


def test_save_and_load(tmp_path: Path) -> None:
    pi = pixel_priors(_random_labels(3, (4, 6), 19, seed=4), progress=False)
    path = tmp_path / "ckpt" / "priors.pt"
    save_priors(path, pi)
    assert torch.equal(read_priors_file(path, CLASS_NAMES)["priors"], pi)
    assert [p.name for p in path.parent.iterdir()] == ["priors.pt"]  # no temp file left
    with pytest.raises(FileNotFoundError, match=r"missing\.pt"):
        read_priors_file(tmp_path / "missing.pt", CLASS_NAMES)
    (tmp_path / "junk.pt").write_bytes(b"junk")
    with pytest.raises(ValueError, match=r"junk\.pt.*; expected a pixel-priors \.pt file"):
        read_priors_file(tmp_path / "junk.pt", CLASS_NAMES)
    torch.save({"priors": pi}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not a pixel-priors file"):
        read_priors_file(tmp_path / "other.pt", CLASS_NAMES)
    renamed = ("street", *CLASS_NAMES[1:])
    with pytest.raises(ValueError, match="expected"):
        read_priors_file(path, renamed)


def _uniform(n: int = 19, size: tuple[int, int] = (4, 6)) -> torch.Tensor:
    return torch.full((n, *size), 1 / n)


def _spoilt(value: float) -> torch.Tensor:
    priors = _uniform()
    priors[CLASS_NAMES.index("road"), 2, 3] = value
    return priors


@pytest.mark.parametrize(
    ("priors", "message"),
    [
        (_spoilt(float("nan")), r"1 value that is not finite and > 0 \(nan for class 'road' at r"),
        (_spoilt(float("inf")), r"not finite and > 0 \(inf for class 'road' at row 2, column 3\)"),
        (_spoilt(0.0), r"not finite and > 0 \(0.0 for class 'road'"),
        (_spoilt(-0.5), r"not finite and > 0 \(-0.5 for class 'road'"),
        (torch.full((19, 4, 6), float("nan")), r"hold 456 values that are not finite"),
        (_uniform(18), r"must be \(19, H, W\) for the 19 classes, got shape \(18, 4, 6\)"),
        (_uniform()[:, 0], r"must be \(19, H, W\) .* got shape \(19, 6\)"),
        (_uniform().numpy(), r"must be a torch tensor \(19, H, W\), got ndarray"),
    ],
)
def test_priors_are_checked_wherever_they_enter(tmp_path: Path, priors, message: str) -> None:
    """A file (read or checked before the run), the maps every rule and RoI reads (a
    checkpoint's or the Python API's tensor): the same one-line ValueError."""
    with pytest.raises(ValueError, match=message):
        PriorMaps(priors)
    if isinstance(priors, torch.Tensor):
        path = tmp_path / "bad.pt"
        torch.save(
            {
                "format": "costseg-pixel-priors-v1",
                "class_names": list(CLASS_NAMES),
                "priors": priors,
                "settings": None,
            },
            path,
        )
        for read in (read_priors_file, lambda p, c: check_priors_file(str(p), c)):
            with pytest.raises(ValueError, match=rf"the priors in '{path}' (hold|must be)") as err:
                read(path, CLASS_NAMES)
            assert "\n" not in str(err.value)


def test_nan_priors_no_longer_reach_the_roi_map() -> None:
    """The issue's case: NaN priors made NaN pixels street; now they are refused."""
    priors = _spoilt(float("nan"))
    assert roi_map(priors)[2, 3] == 1  # what a silent use would give (argmax of NaN: street)
    with pytest.raises(ValueError, match="not finite"):
        PriorMaps(priors).roi_map()


def test_priors_note_on_few_labels_and_on_the_evaluated_labels(tmp_path: Path, capsys) -> None:
    val = tmp_path / "gtFine" / "val"
    evaluated = [val / "city" / f"{i}_gtFine_labelIds.png" for i in range(6)]
    assert priors_note(50) is None and priors_note(None) is None
    assert "on 49 labels (fewer than 50)" in priors_note(49)
    own = priors_note(3000, val, evaluated)
    assert own is not None and f"on the evaluated images' own labels ({val})" in own
    assert priors_note(3000, tmp_path / "gtFine" / "train", evaluated) is None
    assert priors_note(3000, tmp_path / "gtFine" / "va", evaluated) is None  # not a prefix match
    both = priors_note(6, tmp_path, evaluated)
    assert "6 labels" in both and "own labels" in both and "\n" not in both

    # a Cityscapes-layout dataset lists its (image, label) paths
    dataset = SimpleNamespace(files=[(label, label) for label in evaluated])

    path = tmp_path / "val_priors.pt"
    save_priors(path, _uniform(), settings={"labels": str(val), "num_labels": 6})
    description = {"priors": {"file": str(path)}}
    note_priors(description, str(path), dataset)
    printed = capsys.readouterr().out.strip()
    assert printed == description["priors"]["note"] == priors_note(6, val, evaluated)
    counted = {"priors": {"labels": 3000, "split": "train"}}
    note_priors(counted, None, dataset)
    assert "note" not in counted["priors"] and capsys.readouterr().out == ""


def _counts(labels: list[torch.Tensor], n: int) -> np.ndarray:
    """(n, H, W) class counts with plain loops, 255 ignored."""
    h, w = labels[0].shape
    out = np.zeros((n, h, w))
    for label in labels:
        for y in range(h):
            for x in range(w):
                if int(label[y, x]) != 255:
                    out[int(label[y, x]), y, x] += 1
    return out


def test_smoothing_matches_scipy_on_counts() -> None:
    # Counts are smoothed (then divided by the smoothed total), as in the paper's authors' code.
    labels = _random_labels(count=5, size=(9, 11), n=3, seed=5)
    labels[0][:, :4] = labels[1][:, :4] = 255  # unevenly labelled locations weigh less
    eps, sigma = 1e-4, 1.5
    counts = gaussian_filter(_counts(labels, 3), sigma=(0, sigma, sigma), mode="nearest")
    freq = np.maximum(counts / counts.sum(axis=0, keepdims=True), eps)
    want = torch.from_numpy(freq / freq.sum(axis=0, keepdims=True))
    got = pixel_priors(labels, num_classes=3, sigma=sigma, eps=eps, progress=False)
    torch.testing.assert_close(got.double(), want, atol=1e-6, rtol=0)
    # Smoothing the frequencies instead would give something else on this case.
    raw = _counts(labels, 3) / _counts(labels, 3).sum(axis=0, keepdims=True).clip(min=1)
    other = gaussian_filter(raw, sigma=(0, sigma, sigma), mode="nearest")
    assert np.abs(other / other.sum(0) - want.numpy()).max() > 1e-3


def test_hand_case_smoothing_spreads_one_pixel() -> None:
    # One labelled location (class 1) in a 1 x 5 row: σ = 1 spreads it, and since the total is
    # smoothed the same way, every location within reach is all class 1 before the floor.
    label = torch.full((1, 5), 255)
    label[0, 2] = 1
    pi = pixel_priors([label], num_classes=2, sigma=1.0, eps=1e-5, progress=False)
    torch.testing.assert_close(pi[1], torch.full((1, 5), 1 / (1 + 1e-5)))
    far = torch.full((1, 12), 255)
    far[0, 0] = 0  # beyond 4σ = 4 pixels the kernel ends: no information, uniform
    pi = pixel_priors([far], num_classes=2, sigma=1.0, progress=False)
    torch.testing.assert_close(pi[:, 0, 11], torch.tensor([0.5, 0.5]))
    assert pi[0, 0, 3] > 0.99


def test_default_sigma_and_max_labels() -> None:
    labels = _random_labels(count=4, size=(64, 20), n=4, seed=6)
    assert default_sigma(64) == 5.0 and default_sigma(1024) == 80.0
    default = pixel_priors(labels, num_classes=4, progress=False)
    torch.testing.assert_close(default, pixel_priors(labels, 4, sigma=5.0, progress=False))
    assert not torch.allclose(default, pixel_priors(labels, 4, sigma=0, progress=False))
    capped = pixel_priors(iter(labels), 4, sigma=0, progress=False, max_labels=2)
    torch.testing.assert_close(capped, pixel_priors(labels[:2], 4, sigma=0, progress=False))
    with pytest.raises(ValueError, match="max_labels"):
        pixel_priors(labels, 4, max_labels=0)
    with pytest.raises(ValueError, match="sigma"):
        pixel_priors(labels, 4, sigma=-1.0)


def test_cached_priors_reused_and_recomputed(tmp_path: Path) -> None:
    labels = _random_labels(count=3, size=(16, 8), n=19, seed=7)
    calls = []

    def factory() -> list[torch.Tensor]:
        calls.append(1)
        return labels

    cache = tmp_path / "out" / "priors.pt"
    settings = {"root": tmp_path / "data", "split": "train", "size": (16, 8), "cap": None}
    first = cached_priors(factory, cache, settings, progress=False)
    assert (first.reused, first.num_labels, first.sigma, len(calls)) == (False, 3, 1.25, 1)
    torch.testing.assert_close(first.priors, pixel_priors(labels, progress=False))
    assert torch.equal(read_priors_file(cache, CLASS_NAMES)["priors"], first.priors)
    # Same settings (a tuple read back as a list, a path as its string): reused, no labels read.
    same = {**settings, "size": [16, 8], "root": str(tmp_path / "data")}
    again = cached_priors(factory, cache, same, progress=False)
    assert again.reused and len(calls) == 1 and torch.equal(again.priors, first.priors)
    assert (again.num_labels, again.sigma) == (3, 1.25)
    # Other label source or other smoothing: recomputed and the cache replaced.
    other = cached_priors(factory, cache, {**settings, "split": "val"}, progress=False)
    assert not other.reused and len(calls) == 2
    raw = cached_priors(factory, cache, {**settings, "split": "val"}, sigma=0, progress=False)
    assert not raw.reused and len(calls) == 3
    torch.testing.assert_close(raw.priors, pixel_priors(labels, sigma=0, progress=False))
    assert cached_priors(factory, cache, {**settings, "split": "val"}, sigma=0).reused
    # A file that is no priors file is replaced, not an error.
    cache.write_bytes(b"junk")
    assert not cached_priors(factory, cache, settings, progress=False).reused
    assert torch.equal(read_priors_file(cache, CLASS_NAMES)["priors"], first.priors)
