"""Tests for costseg.networks.probs_files: per-image probability files (docs/definitions.md §8)."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from costseg.networks.probs_files import find_probs_file, load_probs, save_probs

STEM = "frankfurt_000000_000294"


def _probs(n: int = 19, h: int = 6, w: int = 10, seed: int = 0) -> torch.Tensor:
    logits = torch.randn(n, h, w, generator=torch.Generator().manual_seed(seed)) * 3
    return logits.softmax(0)


@pytest.mark.parametrize("suffix", [".npz", ".pt"])
def test_save_load_round_trip_in_float16(tmp_path: Path, suffix: str) -> None:
    probs = _probs()
    path = save_probs(tmp_path / f"{STEM}{suffix}", probs)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{STEM}{suffix}"]  # no temp file left
    if suffix == ".npz":
        stored = np.load(path)["probs"]
    else:
        stored = torch.load(path, weights_only=True)["probs"].numpy()
    assert stored.dtype == np.float16 and stored.shape == (19, 6, 10)
    loaded = load_probs(path, size=(6, 10))
    assert loaded.dtype == torch.float32
    torch.testing.assert_close(loaded, probs.half().float(), atol=0, rtol=0)
    assert (loaded - probs).abs().max() < 1e-3  # float16 keeps ~3 decimals


def test_save_overwrites_atomically(tmp_path: Path) -> None:
    path = tmp_path / f"{STEM}.npz"
    save_probs(path, _probs(seed=1))
    save_probs(path, _probs(seed=2))
    torch.testing.assert_close(load_probs(path), _probs(seed=2).half().float())


@pytest.mark.parametrize("suffix", [".npz", ".pt"])
def test_logits_files_are_softmaxed(tmp_path: Path, suffix: str) -> None:
    logits = torch.randn(19, 5, 7, generator=torch.Generator().manual_seed(3)).half()
    path = tmp_path / f"{STEM}{suffix}"
    if suffix == ".npz":
        np.savez(path, logits=logits.numpy())
    else:
        torch.save({"logits": logits}, path)
    expected = np.exp(logits.double().numpy())
    expected /= expected.sum(0, keepdims=True)
    torch.testing.assert_close(load_probs(path).double(), torch.from_numpy(expected))


def test_find_probs_file_flat_and_per_city(tmp_path: Path) -> None:
    flat = save_probs(tmp_path / f"{STEM}.pt", _probs())
    assert find_probs_file(tmp_path, STEM) == flat
    nested = save_probs(tmp_path / "lindau" / "lindau_000000_000019.npz", _probs())
    assert find_probs_file(tmp_path, "lindau_000000_000019") == nested
    with pytest.raises(FileNotFoundError, match="no probabilities for image aachen_000000_000019"):
        find_probs_file(tmp_path, "aachen_000000_000019")
    save_probs(tmp_path / f"{STEM}.npz", _probs())
    with pytest.raises(ValueError, match="several probability files"):
        find_probs_file(tmp_path, STEM)


def _write(path: Path, **arrays: np.ndarray) -> Path:
    np.savez(path, **arrays)
    return path


def test_bad_files_give_one_clear_line(tmp_path: Path) -> None:
    good = _probs().numpy()
    cases = {
        "wrong_shape": (
            _write(tmp_path / "a.npz", probs=good[0]),
            r"shape \(6, 10\); expected \(N, H, W\)",
        ),
        "4d": (_write(tmp_path / "b.npz", probs=good[None]), r"expected \(N, H, W\)"),
        "int": (
            _write(tmp_path / "c.npz", probs=(good * 100).astype(np.int64)),
            "dtype int64; expected floating",
        ),
        "classes": (
            _write(tmp_path / "d.npz", probs=good[:18] / good[:18].sum(0)),
            "holds 18 classes; expected 19",
        ),
        "no_key": (
            _write(tmp_path / "e.npz", scores=good),
            "exactly one tensor named 'probs' or 'logits'",
        ),
        "both": (_write(tmp_path / "f.npz", probs=good, logits=good), "exactly one tensor"),
        "not_probs": (_write(tmp_path / "g.npz", probs=good * 2), "do not sum to 1"),
        "nan": (_write(tmp_path / "h.npz", probs=np.full_like(good, np.nan)), "do not sum to 1"),
    }
    for name, (path, message) in cases.items():
        with pytest.raises(ValueError, match=message) as info:
            load_probs(path)
        assert str(path) in str(info.value) and "\n" not in str(info.value), name
    with pytest.raises(ValueError, match=r"the image's labels are 8x10"):
        load_probs(_write(tmp_path / "i.npz", probs=good), size=(8, 10))


def test_files_of_the_wrong_kind(tmp_path: Path) -> None:
    (tmp_path / "text.npz").write_text("not a zip file")
    (tmp_path / "text.pt").write_text("not a torch file")
    with open(tmp_path / "obj.pt", "wb") as f:
        pickle.dump({"probs": object()}, f, protocol=2)
    torch.save(torch.zeros(19, 2, 2), tmp_path / "bare.pt")  # a tensor, but probs or logits?
    (tmp_path / "probs.png").write_bytes(b"\x89PNG")
    for name in ("text.npz", "text.pt", "obj.pt", "bare.pt", "probs.png"):
        with pytest.raises(ValueError, match=name.replace(".", r"\.")) as info:
            load_probs(tmp_path / name)
        assert "\n" not in str(info.value)
    with pytest.raises(FileNotFoundError, match=r"missing\.npz"):
        load_probs(tmp_path / "missing.npz")


def test_save_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"\.npz or \.pt"):
        save_probs(tmp_path / "x.npy", _probs())
    with pytest.raises(ValueError, match=r"\(N, H, W\)"):
        save_probs(tmp_path / "x.npz", _probs()[0])
    with pytest.raises(ValueError, match=r"\(N, H, W\)"):
        save_probs(tmp_path / "x.npz", torch.zeros(19, 2, 2, dtype=torch.int64))
