"""The value system chosen with a guarantee (Learn-then-Test, docs/definitions.md §7):
``guarantee.json`` and ``guarantee_cost.yaml``."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from costseg.calibration.guarantee import LTTResult
from costseg.classes import CLASS_NAMES
from costseg.costs import save_cost
from costseg.metrics.names import PIXEL_RATES
from costseg.report.files import write_json
from costseg.report.results import EvalResults
from costseg.report.sections import Result, Section
from costseg.report.sweep import SWEEP_ROIS
from costseg.rules import RuleGroup


@dataclass
class Certificate(Result):
    """The value system chosen with a guarantee (Learn-then-Test over a rule group).

    Attributes:
        group: the candidates (grid points, α values, or rules at defer costs).
        ltt: the test's outcome (p-values, risks, images used and left out).
        chosen: index of the certified candidate with the best ``maximize`` on the
            calibration images, or None when nothing is certified.
        objective: (K,) pooled value of ``maximize`` on the calibration images.
        target, maximize: the texts asked; ``num_images``: calibration images.
    """

    group: RuleGroup
    ltt: LTTResult
    chosen: int | None
    objective: torch.Tensor
    target: str
    maximize: str
    num_images: int

    def write(self, results: EvalResults) -> Section:
        """``guarantee.json`` (and ``guarantee_cost.yaml`` for a certified cost matrix)."""
        ltt, group, out = self.ltt, self.group, results.output_dir
        record = {
            "target": self.target,
            "maximize": self.maximize,
            "alpha": ltt.alpha,
            "delta": ltt.delta,
            "method": ltt.method,
            "bound": ltt.bound,
            "calibration_images": self.num_images,
            "candidates": len(group.names),
            "certified": [group.columns[i] for i in ltt.valid.tolist()],
            "found": self.chosen is not None,
        }
        if self.chosen is None:
            write_json(out / "guarantee.json", record)
            return Section(
                console=[
                    f"no value system is certified for {self.target} at δ = {ltt.delta} "
                    f"with {self.num_images} calibration images"
                ]
            )
        k = self.chosen
        record |= {
            "chosen": group.columns[k],
            "calibration_risk": float(ltt.risk[k]),
            "pvalue": float(ltt.pvalues[k]),
            "images_used": int(ltt.n[k]),
            "images_left_out": int(ltt.n_undefined[k]),
            "calibration_value": float(self.objective[k]),
            "report": _reported(results, group, k),
        }
        matrix = group.cost(k)
        if matrix is not None:
            save_cost(out / "guarantee_cost.yaml", matrix, "guaranteed")
            record["matrix"] = matrix.tolist()
        write_json(out / "guarantee.json", record)
        line = (
            f"certified for {self.target} with P(risk > {ltt.alpha:.3g}) <= {ltt.delta}: "
            f"{group.names[k]} (calibration risk {ltt.risk[k]:.4f} on {ltt.n[k]} images, "
            f"{ltt.n_undefined[k]} left out; {self.maximize} {float(self.objective[k]):.4f}); "
            f"{len(ltt.valid)} of {len(group.names)} candidates certified"
        )
        return Section(console=[line])


def _reported(results: EvalResults, group: RuleGroup, k: int) -> dict:
    """The chosen rule's precision and recall on the reported images (RoI 0-2, --classes)."""
    pixels = results.result_of(group).pixels
    return {
        f"{CLASS_NAMES[cls]}/roi{roi}": {m: pixels[m][k, roi, cls].item() for m in PIXEL_RATES}
        for cls in results.class_ids
        for roi in SWEEP_ROIS
    }
