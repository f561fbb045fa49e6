"""One pass over a dataset: the network once per image, every decision rule, all metrics.

Rules come in groups (:class:`RuleGroup`): the named rules of ``--cost`` and, for a sweep, the
grid of mixtures. Each group decides from the same softmax and feeds its own metrics. Under
``torchrun`` every process takes its own share of the images and the metrics' sums are merged.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset, Subset
from tqdm import tqdm

from costseg.metrics import RoIPrecisionRecall, SegmentErrors
from costseg.module import SegmentationModule

Decider = Callable[[torch.Tensor, torch.Tensor | None], torch.Tensor]
BatchHook = Callable[[int, torch.Tensor, torch.Tensor, list[torch.Tensor]], None]


@dataclass
class RuleGroup:
    """K rules decided together: ``decide(probs (B,N,H,W), priors) → (B, K, H, W)``."""

    names: list[str]
    decide: Decider
    heatmaps: bool = True  # FP/FN location maps (off for sweeps of hundreds of rules)


def shard(dataset: Dataset) -> Dataset:
    """This process's share of ``dataset`` under torch.distributed (no padding, no repeats)."""
    if not (dist.is_available() and dist.is_initialized()):
        return dataset
    rank, world = dist.get_rank(), dist.get_world_size()
    return Subset(dataset, range(rank, len(dataset), world))


def evaluate(
    module: SegmentationModule,
    loader: DataLoader,
    groups: Sequence[RuleGroup],
    classes: Sequence[int],
    heatmap_size: tuple[int, int] | None = None,
    on_batch: BatchHook | None = None,
    progress: bool = True,
) -> list[dict[str, dict[str, torch.Tensor]]]:
    """Evaluate every group of rules on ``loader``.

    Args:
        module: the trained model (eval mode is set here), with its priors.
        loader: yields (images (B,3,H,W) uint8, labels (B,H,W) int64).
        groups: the rule groups.
        classes: class indices for the segment metrics (e.g. person, building).
        heatmap_size: (h, w) of the FP/FN maps; None = label size.
        on_batch: called as ``on_batch(batch_index, images, labels, preds_per_group)``.
        progress: show a progress bar.

    Returns:
        per group ``{"pixels": RoIPrecisionRecall.compute(), "segments": SegmentErrors.compute()}``.
    """
    module.eval()
    device = module.device
    metrics = [
        (
            RoIPrecisionRecall(module.hparams.num_classes, num_rules=len(g.names)).to(device),
            SegmentErrors(
                classes, num_rules=len(g.names), heatmap_size=heatmap_size if g.heatmaps else (0, 0)
            ).to(device),
        )
        for g in groups
    ]
    with torch.inference_mode():
        for index, (images, labels) in enumerate(tqdm(loader, "evaluate", disable=not progress)):
            images, labels = images.to(device), labels.to(device)
            probs = module(images).float().softmax(1)
            priors, roi = module.priors_at(labels.shape[-2:]) or (None, None)
            preds = [g.decide(probs, priors) for g in groups]
            for (pixels, segments), p in zip(metrics, preds, strict=True):
                pixels.update(p, labels, roi)
                segments.update(p, labels, roi)
            if on_batch is not None:
                on_batch(index, images, labels, preds)
    return [{"pixels": p.compute(), "segments": s.compute()} for p, s in metrics]


def result_rows(
    names: Sequence[str],
    result: dict[str, dict[str, torch.Tensor]],
    classes: Sequence[int],
    class_names: Sequence[str],
    rois: Sequence[int] = (0, 1, 2, 3, 4),
) -> list[dict]:
    """Flat rows (rule × class × RoI) of precision, recall, FP/FN segments and the rule's mIoU."""
    pixels, segments = result["pixels"], result["segments"]
    rows = []
    for k, name in enumerate(names):
        for c, cls in enumerate(classes):
            for r in rois:
                rows.append(
                    {
                        "matrix": name,
                        "class": class_names[cls],
                        "roi": r,
                        "precision": pixels["precision"][k, r, cls].item(),
                        "recall": pixels["recall"][k, r, cls].item(),
                        "fp_segments": int(segments["fp"][k, c, r]),
                        "fn_segments": int(segments["fn"][k, c, r]),
                        "n_pred_segments": int(segments["n_pred"][k, c, r]),
                        "n_gt_segments": int(segments["n_gt"][k, c, r]),
                        "miou": pixels["miou"][k].item(),
                    }
                )
    return rows
