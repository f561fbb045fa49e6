"""Unknown objects in the procedural scenes and the anomaly metrics (docs/definitions.md §17)."""

from __future__ import annotations

import pytest
import torch

from costseg.data.toy import StreetScenes

SIZE = (64, 128)


def test_unknown_objects_leave_the_scene_around_them_unchanged():
    plain, unknown = StreetScenes("val", 6, SIZE), StreetScenes("val", 6, SIZE, anomalies=True)
    assert unknown.has_anomalies and not plain.has_anomalies
    for i in range(6):
        image, label, mask = unknown.with_anomalies(i)
        clean_image, clean_label = plain[i]
        assert set(mask.unique().tolist()) <= {0, 1, 255} and (mask == 1).any()
        objects = mask == 1
        assert (label[objects] == 255).all()  # no Cityscapes class is right there
        assert torch.equal(label[~objects], clean_label[~objects])  # the same scene around them
        assert torch.equal(mask == 255, (label == 255) & ~objects)
        assert not torch.equal(image, clean_image)
        assert torch.equal(unknown[i][0], image) and torch.equal(unknown[i][1], label)
        _, _, ids = unknown.with_instances(i)
        assert (ids[objects] == 0).all()  # unlabelled in Cityscapes' instance encoding


def test_scenes_without_unknown_objects_have_no_mask():
    with pytest.raises(ValueError, match="anomalies=True"):
        StreetScenes("val", 1, SIZE).with_anomalies(0)
