"""Two CPU processes (gloo), each seeing part of the data, give the single-process metrics: the
pixel and segment metrics, calibration and instance misses; and a training step of every loss
gives the loss and gradients of one process on the whole batch (:mod:`test_losses_ddp`)."""

from __future__ import annotations

import os
import socket

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from test_calibration import run_ece
from test_instances import CLASSES, predictions, roi_blocks, scenes
from test_losses_ddp import check_losses, expected_losses

from costseg.metrics import InstanceMisses, RoIPrecisionRecall, SegmentErrors

pytestmark = pytest.mark.e2e  # DDP processes

WORLD = 2


def make_data() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    coarse = torch.rand(3, 4, 19, 3, 4, generator=g)  # (image, rule, class, h, w)
    preds = torch.nn.functional.interpolate(coarse.flatten(0, 1), (12, 16), mode="bilinear")
    preds = preds.argmax(1).unflatten(0, (3, 4))
    target = preds[:, 0].clone()
    target[torch.rand(3, 12, 16, generator=g) < 0.3] = 255
    target[:, :4] = 3  # a band of class 3: FN segments for rules that miss it
    return preds, target, torch.randint(0, 5, (12, 16), generator=g)


def make_metrics() -> list[RoIPrecisionRecall | SegmentErrors]:
    return [
        RoIPrecisionRecall(num_rules=4),
        SegmentErrors(classes=(3, 7), num_rules=4),
        SegmentErrors(classes=(3,), num_rules=4, heatmap_size=(6, 8)),
    ]


def run_metrics(preds, target, roi, batches) -> list[dict[str, torch.Tensor]]:
    metrics = make_metrics()
    for metric in metrics:
        for batch in batches:
            metric.update(preds[batch], target[batch], roi)
    return [metric.compute() for metric in metrics]


def instance_metrics(batches: list[list[int]]) -> list[dict[str, torch.Tensor]]:
    labels, ids, _ = scenes()
    preds, roi = predictions(labels), roi_blocks()
    metric = InstanceMisses(CLASSES, 3, heatmap_size=(8, 16))
    for batch in batches:
        metric.update(preds[batch], labels[batch], ids[batch], roi)
    return [metric.compute()]


def pixel_metrics(batches: list[list[int]]) -> list[dict[str, torch.Tensor]]:
    return run_metrics(*make_data(), batches)


# Each family's metrics of the given batches; rank 0 sees two batches, rank 1 the rest.
FAMILIES = {
    "pixels and segments": (pixel_metrics, ([[0], [1]], [[2]])),
    "calibration": (run_ece, ([[0], [1]], [[2]])),
    "instances": (instance_metrics, ([[0], [1]], [[2, 3]])),
}


def worker(
    rank: int, port: int, expected: dict[str, list[dict[str, torch.Tensor]]], losses
) -> None:
    os.environ |= {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}
    dist.init_process_group("gloo", rank=rank, world_size=WORLD)
    try:
        check_losses(rank, losses)
        for family, (metrics, shares) in FAMILIES.items():
            for got, want in zip(metrics(shares[rank]), expected[family], strict=True):
                assert got.keys() == want.keys(), family
                for key in want:
                    torch.testing.assert_close(
                        got[key], want[key], rtol=0, atol=0, equal_nan=True, msg=family + key
                    )
    finally:
        dist.destroy_process_group()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_process_ddp_equals_single_process() -> None:
    """One pair of processes checks every family (each spawn costs seconds)."""
    expected = {family: metrics(a + b) for family, (metrics, (a, b)) in FAMILIES.items()}
    assert expected["pixels and segments"][1]["fn"].sum() > 0
    assert expected["pixels and segments"][1]["fp"].sum() > 0
    assert expected["instances"][0]["missed_instances"].sum() > 0
    mp.spawn(worker, args=(free_port(), expected, expected_losses()), nprocs=WORLD, join=True)
