"""Anomaly metrics (docs/definitions.md §17), as SegmentMeIfYouCan (Chan et al. 2021) defines
them, on an anomaly mask (1 = unknown object, 0 = known, 255 = void) and per-pixel anomaly
scores in [0, 1].

* Pixel level, from histograms of the scores of anomaly and known pixels (``BINS`` bins of
  [0, 1], so batches and processes add up): AUROC, average precision (the area under the
  precision-recall curve as ``sklearn.metrics.average_precision_score`` sums it) and the false
  positive rate at 95 % true positive rate. Scores equal within a bin count as ties.
* Component level, as the benchmark's code computes them
  (``road_anomaly_benchmark/metrics/instance_segmentation.py``): the prediction ``score > δ``
  without void pixels, 8-connected components; predicted components smaller than one size and
  ground-truth components smaller than another (their pixels become void) are dropped first
  (:func:`size_thresholds`). Per ground-truth component k the sIoU ``|k ∩ K̂| / |(k ∪ K̂) \\ A|``
  (K̂ the predicted components that meet k, A the pixels of the other ground-truth components),
  per predicted component the PPV (its share of evaluated pixels inside ground-truth
  components); at each τ of ``TAUS`` a ground-truth component with sIoU ≥ τ is a true positive
  (else a false negative) and a predicted one with PPV < τ a false positive;
  F1(τ) = 2 TP / (2 TP + FN + FP), mean F1 its mean over ``TAUS``.

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
# 0.25, 0.30, ..., 0.75 as the benchmark's ``np.linspace`` makes them (its 0.6 is 0.6 + 1e-16)
TAUS = tuple(np.linspace(0.25, 0.75, 11).tolist())
DELTAS = tuple(round(0.1 * i, 1) for i in range(1, 10))  # thresholds of the anomaly prediction
EIGHT = np.ones((3, 3), dtype=bool)
# the benchmark's least sizes (predicted, ground-truth component) in pixels, per track, and the
# area of the images they are meant for (1024 x 2048, Cityscapes' and the AnomalyTrack's)
TRACKS = {"anomaly": (500, 100), "obstacle": (50, 10)}
BENCHMARK_AREA = 1024 * 2048
TRACK = "anomaly"  # costseg's: unknown objects anywhere in the scene, not only on the road


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


def size_thresholds(track: str, height: int, width: int) -> tuple[float, float]:
    """The least sizes, in pixels, of a predicted and of a ground-truth component on an image of
    ``height`` x ``width``: the track's sizes of :data:`TRACKS` times the image's area over
    :data:`BENCHMARK_AREA`, kept as floats (a component counts when its size is not below).

    >>> size_thresholds("anomaly", 128, 256)   # 500 and 100 pixels at 1024 x 2048, / 64
    (7.8125, 1.5625)
    """
    if track not in TRACKS:
        raise ValueError(f"unknown track {track!r}: choose from {', '.join(TRACKS)}")
    scale = height * width / BENCHMARK_AREA
    return tuple(size * scale for size in TRACKS[track])


def ground_truth_components(mask: np.ndarray, min_size: float = 0) -> tuple[np.ndarray, np.ndarray]:
    """The unknown objects (mask 1) as SegmentMeIfYouCan evaluates them: (H, W) ids of their
    8-connected components, 0 outside them and on those smaller than ``min_size`` pixels; and
    the (H, W) bool pixels evaluated: neither void nor in such a small component (it is void).
    """
    ids, _ = ndimage.label(mask == 1, structure=EIGHT)
    small = np.bincount(ids.ravel()) < min_size
    small[0] = False
    voided = small[ids]
    return np.where(voided, 0, ids), (mask != IGNORE_INDEX) & ~voided


def component_counts(
    prediction: np.ndarray,
    mask: np.ndarray,
    min_sizes: tuple[float, float] = (0, 0),
    ground_truth: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(len(TAUS) + 1, 4) float64 of one image: rows per τ (TP, FN, FP, 0), and a last row
    (Σ sIoU, ground-truth components, Σ PPV, predicted components).

    Args:
        prediction: (H, W) bool anomaly prediction (``score > δ``).
        mask: (H, W) anomaly mask (1, 0, 255).
        min_sizes: the least sizes of a predicted and a ground-truth component
            (:func:`size_thresholds`).
        ground_truth: :func:`ground_truth_components` of ``mask`` and ``min_sizes[1]``, if known.
    """
    gt, evaluated = ground_truth or ground_truth_components(mask, min_sizes[1])
    # predicted components are sized before the small objects become void, as the benchmark does
    pred, _ = ndimage.label(prediction & (mask != IGNORE_INDEX), structure=EIGHT)
    small = np.bincount(pred.ravel()) < min_sizes[0]
    small[0] = True
    pred = np.where(small[pred], 0, pred)
    gt, pred = gt[evaluated], pred[evaluated]
    overlap = _overlap(gt, pred)  # [gt, pred] pixels, rows and columns of present components
    siou, ppv = _siou(overlap), overlap[1:, 1:].sum(0) / overlap[:, 1:].sum(0)
    out = np.zeros((len(TAUS) + 1, 4))
    for t, tau in enumerate(TAUS):
        out[t, :3] = (siou >= tau).sum(), (siou < tau).sum(), (ppv < tau).sum()
    out[-1] = siou.sum(), len(siou), ppv.sum(), len(ppv)
    return out


def _overlap(gt: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """(1 + ground-truth components, 1 + predicted components) pixel counts of the ids ``gt`` and
    ``pred`` of the same pixels; row and column 0: no component; ids without a pixel dropped."""
    n_gt, n_pred = int(gt.max(initial=0)) + 1, int(pred.max(initial=0)) + 1
    both = np.bincount(gt * n_pred + pred, minlength=n_gt * n_pred).reshape(n_gt, n_pred)
    rows, columns = both.sum(1) > 0, both.sum(0) > 0
    rows[0] = columns[0] = True
    return both[rows][:, columns].astype(np.float64)


def _siou(overlap: np.ndarray) -> np.ndarray:
    """sIoU per ground-truth component of an :func:`_overlap` table."""
    inside = overlap[1:, 1:]  # (n_gt, n_pred) pixels of predicted j in ground-truth i
    meets = (inside > 0).astype(np.float64)
    intersection = inside.sum(1)  # every predicted pixel of i belongs to a component meeting i
    covered = meets @ overlap[:, 1:].sum(0)  # |K̂|: the predicted components meeting i
    others = meets @ inside.sum(0) - intersection  # of K̂, inside the other components
    return intersection / (overlap[1:].sum(1) + covered - intersection - others)


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
