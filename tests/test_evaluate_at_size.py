"""An evaluation of Cityscapes-layout images at 256 × 512, large enough for torch's thread pool
to run (its grain size), finishes with its example figures, under a deadline."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from costseg.checkpoints import find_checkpoint

ROOT = Path(__file__).resolve().parents[1]


def test_an_evaluation_of_256x512_cityscapes_images_finishes_with_its_figures(tiny_run, tmp_path):
    tree, out = tmp_path / "cityscapes", tmp_path / "out"
    script = [sys.executable, str(ROOT / "scripts" / "toy_as_cityscapes.py"), str(tree)]
    subprocess.run(
        [*script, "--train", "1", "--val", "2", "--size", "256", "512", "--workers", "1"],
        check=True,
        capture_output=True,
        timeout=120,
    )
    network = f"costseg:{find_checkpoint(None, runs_dir=tiny_run[2])}"
    command = [sys.executable, str(ROOT / "evaluate.py"), "--network", network]
    command += ["--data_root", str(tree), "--cost", "robotistic", "egoistic", "--defer", "0.3"]
    command += ["--save-probs", "--num_examples", "2", "--no-progress", "--output_dir", str(out)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((out / "results.json").read_text())["images"] == 2
    for i in (0, 1):
        masks = np.asarray(Image.open(out / "figures" / f"masks_{i}.png"))
        # image, ground truth, two rules and the entropy tile, each a 256 × 512 panel or more
        assert masks.shape[1] >= 5 * 256 and masks.std() > 0
