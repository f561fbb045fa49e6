"""scripts/toy_as_cityscapes.py: procedural scenes written in Cityscapes' layout read back."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from costseg.data.cityscapes import CityscapesSegmentation
from costseg.data.toy import StreetScenes

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "toy_as_cityscapes.py"


def test_scenes_round_trip_through_the_cityscapes_reader(tmp_path: Path) -> None:
    size = ["64", "128"]
    args = [str(tmp_path), "--train", "2", "--val", "3", "--size", *size, "--workers", "1"]
    subprocess.run([sys.executable, str(SCRIPT), *args], check=True, capture_output=True)
    stored = CityscapesSegmentation(tmp_path, "val")
    scenes = StreetScenes("val", 3, (64, 128))
    assert len(stored) == 3 and len(CityscapesSegmentation(tmp_path, "train")) == 2
    for (image, label), (toy_image, toy_label) in zip(stored, scenes, strict=True):
        assert torch.equal(image, toy_image)
        assert torch.equal(label, toy_label)
    # Train ids are stored as Cityscapes label ids: road 7, person 24, ignore → unlabeled 0.
    ids = np.asarray(Image.open(stored.files[0][1]))
    road, person, ignore = (scenes[0][1] == k for k in (0, 11, 255))
    assert (ids[road.numpy()] == 7).all() and (ids[person.numpy()] == 24).all()
    assert (ids[ignore.numpy()] == 0).all()
