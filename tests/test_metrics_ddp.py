"""Two CPU processes (gloo), each seeing half of the data, give the single-process metrics."""

from __future__ import annotations

import os
import socket

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from costseg.metrics import RoIPrecisionRecall, SegmentErrors

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


def worker(rank: int, port: int, expected: list[dict[str, torch.Tensor]]) -> None:
    os.environ |= {"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}
    dist.init_process_group("gloo", rank=rank, world_size=WORLD)
    try:
        preds, target, roi = make_data()
        # Rank 0 sees images 0 and 1 (in two batches), rank 1 sees image 2.
        batches = [[0], [1]] if rank == 0 else [[2]]
        for got, want in zip(run_metrics(preds, target, roi, batches), expected, strict=True):
            assert got.keys() == want.keys()
            for key in want:
                torch.testing.assert_close(got[key], want[key], rtol=0, atol=0, equal_nan=True)
    finally:
        dist.destroy_process_group()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_process_ddp_equals_single_process() -> None:
    preds, target, roi = make_data()
    expected = run_metrics(preds, target, roi, [[0, 1, 2]])
    assert expected[1]["fn"].sum() > 0 and expected[1]["fp"].sum() > 0
    mp.spawn(worker, args=(free_port(), expected), nprocs=WORLD, join=True)
