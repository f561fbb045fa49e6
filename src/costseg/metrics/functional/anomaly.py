"""Anomaly metrics (docs/definitions.md §17), as SegmentMeIfYouCan (Chan et al. 2021) defines
them, on an anomaly mask (1 = unknown object, 0 = known, 255 = void) and per-pixel anomaly
scores in [0, 1].

* Pixel level, from histograms of the scores of anomaly and known pixels (``BINS`` bins of
  [0, 1], so batches and processes add up): AUROC, average precision (the area under the
  precision-recall curve as ``sklearn.metrics.average_precision_score`` sums it) and the false
  positive rate at 95 % true positive rate. Scores equal within a bin count as ties.
* Component level, for the anomaly prediction ``score >= δ`` (void pixels removed): per
  ground-truth component k the sIoU ``|k ∩ K̂| / |(k ∪ K̂) \\ A|`` (K̂ the predicted components
  that meet k, A the pixels of the other ground-truth components), per predicted component the
  PPV (its share of pixels inside ground-truth components); at each τ of ``TAUS`` a
  ground-truth component with sIoU > τ is a true positive (else a false negative) and a
  predicted one with PPV ≤ τ a false positive; F1(τ) = 2 TP / (2 TP + FN + FP), mean F1 its
  mean over ``TAUS``. Components are 8-connected.

>>> hist = torch.tensor([[3, 1, 0, 0], [0, 0, 1, 3]])   # known, anomaly; 4 bins
>>> {k: round(v, 3) for k, v in pixel_metrics(hist).items()}
{'auroc': 1.0, 'ap': 1.0, 'fpr95': 0.0}
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from costseg.classes import IGNORE_INDEX

BINS = 10_000
TAUS = tuple(round(0.25 + 0.05 * i, 2) for i in range(11))  # 0.25, 0.30, ..., 0.75
DELTAS = tuple(round(0.1 * i, 1) for i in range(1, 10))  # thresholds of the anomaly prediction
EIGHT = np.ones((3, 3), dtype=bool)


def score_histograms(scores: Tensor, mask: Tensor, bins: int = BINS) -> Tensor:
    """(S, 2, bins) int64 counts of the known (0) and anomaly (1) pixels' scores per bin.

    Args:
        scores: (S, B, H, W) scores in [0, 1] (clamped), one map per score.
        mask: (B, H, W) anomaly mask; void (255) pixels count nowhere.
    """
    valid = mask != IGNORE_INDEX
    index = (scores.float().clamp(0, 1) * bins).long().clamp(max=bins - 1)
    rows = (mask.long().clamp(max=1) * bins + index)[:, valid]  # (S, valid pixels)
    out = torch.zeros(scores.shape[0], 2 * bins, dtype=torch.int64, device=scores.device)
    out.scatter_add_(1, rows, torch.ones_like(rows))
    return out.view(-1, 2, bins)


def pixel_metrics(hist: Tensor) -> dict[str, float]:
    """AUROC, AP and FPR at 95 % TPR of one score's (2, bins) histogram (NaN without anomaly or
    known pixels)."""
    known, anomaly = (h.double().flip(0) for h in hist)  # thresholds from the highest bin down
    if known.sum() == 0 or anomaly.sum() == 0:
        return dict.fromkeys(("auroc", "ap", "fpr95"), float("nan"))
    tp, fp = anomaly.cumsum(0), known.cumsum(0)
    tpr, fpr = tp / tp[-1], fp / fp[-1]
    zero = torch.zeros(1, dtype=torch.float64)
    auroc = torch.trapezoid(torch.cat([zero, tpr]), torch.cat([zero, fpr])).item()
    kept = anomaly > 0  # a threshold that adds no anomaly pixel adds nothing to the sum
    precision = tp / (tp + fp).clamp(min=1)
    recall_step = torch.diff(torch.cat([zero, tpr]))
    ap = (recall_step[kept] * precision[kept]).sum().item()
    fpr95 = fpr[tpr >= 0.95][0].item()
    return {"auroc": auroc, "ap": ap, "fpr95": fpr95}


def best_pixel_f1(hist: Tensor, deltas: tuple[float, ...] = DELTAS) -> tuple[int, float]:
    """The index in ``deltas`` of the threshold with the best pixel F1, and that F1
    (SegmentMeIfYouCan chooses the prediction's threshold by the pixel F1)."""
    known, anomaly = hist.double()
    bins = hist.shape[-1]
    f1 = []
    for delta in deltas:
        start = round(delta * bins)
        tp, fp = anomaly[start:].sum(), known[start:].sum()
        fn = anomaly[:start].sum()
        f1.append((2 * tp / (2 * tp + fp + fn)).item() if tp + fp + fn > 0 else float("nan"))
    best = int(np.nanargmax(f1)) if not np.isnan(f1).all() else 0
    return best, f1[best]


def ground_truth_components(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """The 8-connected components of the unknown objects (mask 1): (H, W) ids 1..n, and n."""
    return ndimage.label(mask == 1, structure=EIGHT)


def component_counts(
    prediction: np.ndarray, mask: np.ndarray, ground_truth: tuple[np.ndarray, int] | None = None
) -> np.ndarray:
    """(len(TAUS) + 1, 4) float64 of one image: rows per τ (TP, FN, FP, 0), and a last row
    (Σ sIoU, ground-truth components, Σ PPV, predicted components).

    Args:
        prediction: (H, W) bool anomaly prediction.
        mask: (H, W) anomaly mask (1, 0, 255).
        ground_truth: :func:`ground_truth_components` of ``mask``, if already labelled.
    """
    gt, n_gt = ground_truth_components(mask) if ground_truth is None else ground_truth
    pred, n_pred = ndimage.label(prediction & (mask != IGNORE_INDEX), structure=EIGHT)
    both = np.bincount((gt * (n_pred + 1) + pred).ravel(), minlength=(n_gt + 1) * (n_pred + 1))
    overlap = both.reshape(n_gt + 1, n_pred + 1).astype(np.float64)  # [gt, pred] pixels
    gt_size, pred_size = overlap[1:].sum(1), overlap[:, 1:].sum(0)
    inside = overlap[1:, 1:]  # (n_gt, n_pred) pixels of predicted j in ground-truth i
    meets = inside > 0
    intersection = (inside * meets).sum(1)
    covered = meets.astype(np.float64) @ pred_size  # |K̂(k)|: the predicted components meeting k
    in_gt = inside.sum(0)  # pixels of each predicted component inside some ground truth
    others = meets.astype(np.float64) @ in_gt - intersection  # of K̂(k), inside other components
    union = gt_size + covered - intersection - others
    siou = np.divide(intersection, union, out=np.zeros(n_gt), where=union > 0)
    ppv = np.divide(in_gt, pred_size, out=np.zeros(n_pred), where=pred_size > 0)
    out = np.zeros((len(TAUS) + 1, 4))
    for t, tau in enumerate(TAUS):
        out[t, :3] = (siou > tau).sum(), (siou <= tau).sum(), (ppv <= tau).sum()
    out[-1] = siou.sum(), n_gt, ppv.sum(), n_pred
    return out


def component_metrics(counts: Tensor | np.ndarray) -> dict[str, float]:
    """Mean sIoU, mean PPV and mean F1 over ``TAUS`` of summed :func:`component_counts`."""
    counts = np.asarray(counts, dtype=np.float64)
    tp, fn, fp = counts[:-1, 0], counts[:-1, 1], counts[:-1, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(2 * tp + fn + fp > 0, 2 * tp / (2 * tp + fn + fp), np.nan)
        siou_sum, n_gt, ppv_sum, n_pred = counts[-1]
        return {
            "siou": float(siou_sum / n_gt) if n_gt else float("nan"),
            "ppv": float(ppv_sum / n_pred) if n_pred else float("nan"),
            "mean_f1": float(np.mean(f1)),
        }
