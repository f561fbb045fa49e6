"""AnomalyMetrics: how well per-pixel scores find unknown objects, and what each rule decides on
them (docs/definitions.md §17); the core is :mod:`costseg.metrics.functional.anomaly`.

States (summed across batches and processes): ``histograms`` (S, 2, BINS) of each score over
known and anomaly pixels; ``components`` (S, len(DELTAS), len(TAUS) + 1, 4), SegmentMeIfYouCan's
component counts of the prediction ``score > δ`` at every δ of ``DELTAS``, with the least
component sizes of the benchmark's ``track`` scaled to each image's area; ``decided`` (R, N + 1),
the anomaly pixels each rule labels as each class (the last column: deferred).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from costseg.decision.label_maps import DEFERRED
from costseg.metrics.functional.anomaly import (
    BINS,
    DELTAS,
    TAUS,
    TRACK,
    best_pixel_f1,
    component_counts,
    component_metrics,
    ground_truth_components,
    pixel_metrics,
    score_histograms,
    size_thresholds,
)


class AnomalyMetrics(Metric):
    """Pixel AUROC / AP / FPR95 and sIoU / PPV / mean F1 per score; rules' decisions on anomalies.

    Args:
        scores: the names of the anomaly scores, in the order ``update`` gets them.
        num_rules: rules whose label maps ``update`` gets (0: none).
        num_classes: classes N of the label maps.
        track: the SegmentMeIfYouCan track whose least component sizes apply (``TRACKS``).

    >>> metric = AnomalyMetrics(["max_softmax"], num_rules=1, num_classes=3)
    >>> mask, preds = torch.tensor([[[0, 1, 1, 255]]]), torch.tensor([[[[0, 2, 255, 1]]]])
    >>> metric.update(torch.tensor([[[[0.1, 0.9, 0.8, 0.5]]]]), mask, preds)
    >>> out = metric.compute()
    >>> out["scores"]["max_softmax"]["auroc"], out["decided"].tolist()
    (1.0, [[0, 0, 1, 1]])
    """

    full_state_update = False

    def __init__(
        self,
        scores: Sequence[str],
        num_rules: int,
        num_classes: int,
        track: str = TRACK,
        **kwargs: Any,
    ):
        super().__init__(**kwargs)
        size_thresholds(track, 1, 1)  # an unknown track fails here, not at the first batch
        self.names, self.num_classes, self.track = list(scores), num_classes, track
        s = len(self.names)
        self.add_state("histograms", torch.zeros(s, 2, BINS, dtype=torch.int64), "sum")
        shape = (s, len(DELTAS), len(TAUS) + 1, 4)
        self.add_state("components", torch.zeros(shape, dtype=torch.float64), "sum")
        self.add_state("decided", torch.zeros(num_rules, num_classes + 1, dtype=torch.int64), "sum")

    def update(self, scores: Tensor, mask: Tensor, preds: Tensor | None = None) -> None:
        """``scores`` (S, B, H, W) in [0, 1], ``mask`` (B, H, W) (1, 0, 255), ``preds`` (R, B, H,
        W) label maps (255: deferred) or None."""
        self.histograms += score_histograms(scores, mask)
        masks = mask.cpu().numpy()
        sizes = size_thresholds(self.track, *masks.shape[1:])
        objects = [ground_truth_components(m, sizes[1]) for m in masks]  # once, not per δ
        for s, score in enumerate(scores.float().cpu().numpy()):
            for d, delta in enumerate(DELTAS):
                for image, anomaly, gt in zip(score, masks, objects, strict=True):
                    counts = component_counts(image > delta, anomaly, sizes, gt)
                    self.components[s, d] += torch.from_numpy(counts)
        if preds is not None and len(self.decided):
            on = mask == 1
            for r, pred in enumerate(preds):
                picked = pred[on].long()
                picked = torch.where(picked == DEFERRED, self.num_classes, picked)
                counts = torch.bincount(picked, minlength=self.num_classes + 1)
                self.decided[r] += counts.to(self.decided.device)

    def compute(self) -> dict[str, Any]:
        """``scores``: per score its pixel metrics, the δ of the best pixel F1 and the component
        metrics there; ``decided``: (R, N + 1) counts."""
        out = {}
        for s, name in enumerate(self.names):
            best, f1 = best_pixel_f1(self.histograms[s])
            found = pixel_metrics(self.histograms[s]) | {"delta": DELTAS[best], "pixel_f1": f1}
            out[name] = found | component_metrics(self.components[s, best].cpu())
        return {"scores": out, "decided": self.decided.clone()}
