"""Tests for costseg.networks.hf: transformers semantic-segmentation models from a folder.

Skipped when the optional ``transformers`` dependency (the ``hf`` extra) is not installed.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from torch.nn import functional as F

from costseg.networks import load_network


def _images(h: int, w: int, b: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(1)
    return torch.randint(0, 256, (b, 3, h, w), generator=gen, dtype=torch.uint8)


def _tiny_segformer(folder: Path, num_labels: int = 19) -> Path:
    """A tiny random SegFormer and its image processor (non-ImageNet statistics) in ``folder``."""
    import transformers

    config = transformers.SegformerConfig(
        num_labels=num_labels,
        hidden_sizes=[8, 16, 24, 32],
        num_attention_heads=[1, 1, 2, 2],
        depths=[1, 1, 1, 1],
        decoder_hidden_size=16,
    )
    torch.manual_seed(0)
    transformers.SegformerForSemanticSegmentation(config).save_pretrained(folder)
    processor = transformers.SegformerImageProcessor(
        image_mean=[0.5, 0.4, 0.3], image_std=[0.2, 0.25, 0.3]
    )
    processor.save_pretrained(folder)
    return folder


@pytest.fixture
def segformer_dir(tmp_path: Path) -> Path:
    pytest.importorskip("transformers", reason="hf: networks need the hf extra (transformers)")
    return _tiny_segformer(tmp_path / "sf")


@pytest.mark.parametrize("prefix", ["hf", "segformer"])
def test_segformer_gives_transformers_logits(segformer_dir: Path, prefix: str) -> None:
    import transformers

    model = transformers.AutoModelForSemanticSegmentation.from_pretrained(segformer_dir).eval()
    processor = transformers.AutoImageProcessor.from_pretrained(segformer_dir)
    images = _images(64, 96, b=2)
    pixels = processor(
        images=[im.permute(1, 2, 0).numpy() for im in images], do_resize=False, return_tensors="pt"
    )["pixel_values"]
    with torch.no_grad():
        low = model(pixel_values=pixels).logits
        expected = F.interpolate(low, size=(64, 96), mode="bilinear", align_corners=False)
        got = load_network(f"{prefix}:{segformer_dir}")(images)
    assert low.shape[-2:] == (16, 24)  # SegFormer predicts at 1/4 resolution
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-4)


def test_hf_errors(segformer_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import transformers

    with pytest.raises(ValueError, match=r"no config\.json"):
        load_network(f"hf:{tmp_path}")
    bert = tmp_path / "bert"
    transformers.BertConfig(
        hidden_size=8, num_hidden_layers=1, num_attention_heads=1, intermediate_size=8
    ).save_pretrained(bert)
    with pytest.raises(ValueError, match="is not a transformers segmentation model"):
        load_network(f"hf:{bert}")
    with pytest.raises(ValueError, match="predicts 21 classes"):
        load_network(f"hf:{_tiny_segformer(tmp_path / 'voc', num_labels=21)}")
    with pytest.raises(FileNotFoundError, match="model folder not found"):
        load_network(f"hf:{tmp_path / 'nothing'}")
    monkeypatch.setitem(sys.modules, "transformers", None)  # as if the extra were not installed
    with pytest.raises(ValueError, match=r"pip install 'costseg\[hf\]'"):
        load_network(f"hf:{segformer_dir}")
