"""The files of a prediction (docs/usage.md): per image ``panels/<stem>.png``,
``labels/<rule>/<stem>.png`` (Cityscapes label ids), ``color/<rule>/<stem>.png``, optionally
``probs/<stem>.npz`` (with the uncertainty maps, docs/definitions.md §13); per video
``<stem>_panels.mp4`` and ``<stem>_<rule>.mp4``; at the end ``counts.csv`` and
``counts.json``, written last, so a folder holding them is complete. A rule
that may defer (docs/definitions.md §14) writes 255 for its deferred pixels in both label PNGs,
draws them in ``DEFERRED_COLOUR``, and its counts hold its defer cost and deferred share.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

from costseg.classes import CLASS_NAMES, ROI_NAMES, colorize
from costseg.prediction.counts import deferred_pixels, label_counts
from costseg.prediction.panels import overlay, panel
from costseg.prediction.video import VideoWriter
from costseg.report.files import write_csv, write_json, write_png
from costseg.report.outputs import ImageFiles
from costseg.rules import Rule

COUNT_COLUMNS = ("image", "rule", "class", "roi", "pixels", "segments", "deferred")


def defer_text(cost: float | list[float] | None) -> str | None:
    """A rule's :attr:`~costseg.rules.Rule.defer_cost` as the panels state it.

    >>> defer_text(0.25), defer_text([0.1, 0.2]), defer_text(None)
    ('0.25', 'per class', None)
    """
    if cost is None:
        return None
    return "per class" if isinstance(cost, list) else f"{cost:g}"


class PredictionWriter:
    """Writes each image's (or frame's) outputs and gathers the counts.

    Args:
        output_dir: the prediction folder.
        rules: the K rules, in the order of the label maps.
        save_probs: also write ``probs/<stem>.npz`` (float16).
    """

    def __init__(self, output_dir: Path, rules: Sequence[Rule], save_probs: bool) -> None:
        self.output_dir, self.save_probs = output_dir, save_probs
        self.rule_names = [r.name for r in rules]
        self.files = ImageFiles(output_dir, self.rule_names, "labels")
        self.defer_costs = [r.defer_cost for r in rules]
        self.defer_texts = [defer_text(c) for c in self.defer_costs]
        self.counts: dict[str, np.ndarray] = {}  # stem → (K, 2, N, R) pixels and segments
        self.deferred: dict[str, np.ndarray] = {}  # stem → (K, R) deferred pixels
        self.videos: list[VideoWriter] = []

    def image(
        self,
        stem: str,
        image: np.ndarray,
        maps: np.ndarray,
        argmax: np.ndarray,
        roi,
        probs,
        uncertainty: dict | None = None,
        segment_iou: list[np.ndarray] | None = None,
    ) -> None:
        """Files of one image: ``maps`` (K, H, W) train ids (255: deferred), ``argmax`` (H, W),
        ``roi`` (H, W) or None, ``probs`` (N, H, W) tensor, ``uncertainty`` (name → (H, W)
        tensor; saved with ``save_probs``) and per rule its segments' predicted IoU (or None)."""
        out = self.output_dir
        self.files.label_maps(stem, maps)
        for name, labels in zip(self.rule_names, maps, strict=True):
            write_png(out / "color" / name / f"{stem}.png", colorize(labels, deferred=True))
        shown = self.panel(image, maps, argmax, uncertainty, segment_iou)
        write_png(out / "panels" / f"{stem}.png", shown)
        self.count(stem, maps, roi, probs, uncertainty)

    def panel(
        self, image: np.ndarray, maps: np.ndarray, argmax: np.ndarray, uncertainty, segment_iou
    ) -> np.ndarray:
        """The panel of one image or frame (:func:`costseg.prediction.panels.panel`)."""
        shown = None if uncertainty is None else {k: v.numpy() for k, v in uncertainty.items()}
        return panel(image, self.rule_names, maps, argmax, self.defer_texts, shown, segment_iou)

    def count(
        self, stem: str, maps: np.ndarray, roi, probs: torch.Tensor, uncertainty=None
    ) -> None:
        """Count one image's pixels, segments and deferred pixels; write its probabilities (and
        uncertainty maps) with ``save_probs``."""
        self.counts[stem] = np.stack([np.stack(label_counts(m, roi)) for m in maps])
        self.deferred[stem] = np.stack([deferred_pixels(m, roi) for m in maps])
        if self.save_probs:
            self.files.probabilities(stem, probs, uncertainty)

    def open_video(self, stem: str, rate: Fraction) -> None:
        """Start ``<stem>_panels.mp4`` and ``<stem>_<rule>.mp4``."""
        names = [f"{stem}_panels", *(f"{stem}_{n}" for n in self.rule_names)]
        self.videos = [VideoWriter(self.output_dir / f"{n}.mp4", rate) for n in names]

    def frame(
        self, stem: str, image: np.ndarray, maps, argmax, roi, probs, uncertainty, segment_iou
    ) -> None:
        """One video frame: a panel frame, one overlay frame per rule, and its counts."""
        self.videos[0].write(self.panel(image, maps, argmax, uncertainty, segment_iou))
        for video, labels in zip(self.videos[1:], maps, strict=True):
            video.write(overlay(image, labels))
        self.count(stem, maps, roi, probs, uncertainty)

    def close_videos(self, abandon: bool = False) -> None:
        """Finish (or, after an error, drop) the open videos."""
        for video in self.videos:
            video.abandon() if abandon else video.close()
        self.videos = []

    def finish(self, description: dict) -> None:
        """Write ``counts.csv`` and ``counts.json`` (last: they mark a complete folder)."""
        write_csv(self.output_dir / "counts.csv", self._rows(), COUNT_COLUMNS)
        first = next(iter(self.counts.values()), None)
        rois = list(ROI_NAMES[: first.shape[-1]]) if first is not None else ["image"]
        write_json(
            self.output_dir / "counts.json",
            {
                **description,
                "layout": "images[stem][rule] = {pixels, segments}: [class][roi], "
                "{deferred_pixels, deferred}: [roi] (deferred: their share of the RoI's "
                "pixels); segments 8-connected, each in the RoI holding most of its pixels",
                "rules": self.rule_names,
                "defer": dict(zip(self.rule_names, self.defer_costs, strict=True)),
                "classes": list(CLASS_NAMES),
                "rois": rois,
                "images": {
                    stem: {
                        name: {
                            "pixels": c[k, 0].tolist(),
                            "segments": c[k, 1].tolist(),
                            "deferred_pixels": self.deferred[stem][k].tolist(),
                            "deferred": self.deferred_share(stem)[k].tolist(),
                        }
                        for k, name in enumerate(self.rule_names)
                    }
                    for stem, c in self.counts.items()
                },
            },
        )

    def deferred_share(self, stem: str) -> np.ndarray:
        """(K, R) float64: the share of each RoI's pixels that each rule deferred (NaN: a RoI
        without pixels in the image)."""
        deferred = self.deferred[stem]
        total = self.counts[stem][:, 0].sum(1) + deferred
        with np.errstate(invalid="ignore"):
            return deferred / total

    def _rows(self) -> Iterator[dict]:
        for stem, counts in self.counts.items():
            share = self.deferred_share(stem)
            for k, name in enumerate(self.rule_names):
                for c, cls in enumerate(CLASS_NAMES):
                    for r in range(counts.shape[-1]):
                        yield dict(
                            zip(
                                COUNT_COLUMNS,
                                (stem, name, cls, ROI_NAMES[r], counts[k, 0, c, r],
                                 counts[k, 1, c, r], share[k, r]),
                                strict=True,
                            )
                        )  # fmt: skip
