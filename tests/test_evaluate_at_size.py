"""An evaluation of Cityscapes-layout images at 256 × 512, large enough for torch's thread pool
to run (its grain size), finishes with its example figures, under a deadline (its images loaded
by DataLoader workers, its figures drawn by the figure workers, as outside the tests)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import write_cityscapes_item
from interrupts import deadline
from PIL import Image

from costseg.checkpoints import find_checkpoint
from costseg.cli import evaluate_main


@pytest.mark.figures
@pytest.mark.workers  # as users run it: the images loaded by DataLoader workers
def test_an_evaluation_of_256x512_cityscapes_images_finishes_with_its_figures(tiny_run, tmp_path):
    tree, out = tmp_path / "cityscapes", tmp_path / "out"
    for split, item in (("train", 0), ("val", 1), ("val", 2)):
        write_cityscapes_item(tree, split, f"city_000000_00000{item}", item, size=(256, 512))
    network = f"costseg:{find_checkpoint(None, runs_dir=tiny_run[2])}"
    args = ["--network", network, "--data_root", str(tree), "--cost", "robotistic", "egoistic"]
    args += ["--defer", "0.3", "--save-probs", "--num_examples", "2", "--no-progress"]
    with deadline(240, "the evaluation"):
        evaluate_main([*args, "--output_dir", str(out)])
    assert json.loads((out / "results.json").read_text())["images"] == 2
    for i in (0, 1):
        masks = np.asarray(Image.open(out / "figures" / f"masks_{i}.png"))
        # image, ground truth, two rules and the entropy tile side by side
        assert masks.shape[1] >= 5 * 256 and masks.std() > 0
