"""The outputs of ``--conformal`` (docs/definitions.md §18): per anchor rule λ̂, the loss on
the reported images next to α, set sizes, singletons and coverage per class and RoI, in
results.json, table.md, ``conformal.csv``, TensorBoard and two figures (the risk against λ on
the held-out images, the set sizes over the first reported image)."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from matplotlib.figure import Figure

from costseg.calibration.conformal import RiskControl, SetCounts
from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.report.drawing import job
from costseg.report.files import write_csv
from costseg.report.results import EvalResults
from costseg.report.sections import Result, Section
from costseg.report.tables import format_value, markdown_table


@dataclass
class RuleSets:
    """One anchor rule's sets: its risk control on the held-out images, its set counts and
    per-image losses (NaN: nothing counted) on the reported images."""

    name: str
    control: RiskControl
    counts: SetCounts
    losses: torch.Tensor

    def summary(self) -> dict:
        """The record of results.json."""
        c, counts = self.control, self.counts
        counted = self.losses[~self.losses.isnan()]
        by_roi = dict(enumerate(ROI_NAMES))
        return {
            "lambda": c.lam,
            "reached": c.reached,
            "calibration_images": c.n,
            "calibration_left_out": c.left_out,
            "calibration_risk": float(c.risk[c.index]),
            "reported_loss": counted.mean().item() if len(counted) else float("nan"),
            "reported_images": len(counted),
            "mean_set_size": {by_roi[r]: v for r, v in enumerate(counts.mean_size().tolist())},
            "singleton_share": {
                by_roi[r]: v for r, v in enumerate(counts.singleton_share().tolist())
            },
            "coverage": _per_class_and_roi(counts.coverage()),
            "mean_set_size_per_class": _per_class_and_roi(counts.mean_size(per_class=True)),
        }


def conformal_table(record: dict, alpha: float, sets: str, class_ids: Sequence[int]) -> str:
    """table.md's section: per anchor rule (``record``: :meth:`RuleSets.summary` by name) λ̂,
    the risk and loss as fractions (as α), set sizes in classes, singletons and the coverage of
    ``class_ids`` in RoI 1 in %; each header names its unit."""
    rows = []
    for name, r in record.items():
        row = {
            "matrix": name,
            "λ̂": f"{r['lambda']:.3f}" + ("" if r["reached"] else " (not reached)"),
            "calibration images": r["calibration_images"],
            "calibration risk (fraction)": format_value(r["calibration_risk"]),
            "reported loss (fraction)": format_value(r["reported_loss"]),
            "set size (classes)": format_value(r["mean_set_size"][ROI_NAMES[0]]),
            "set size RoI 1 (classes)": format_value(r["mean_set_size"][ROI_NAMES[1]]),
            "singletons (%)": format_value(r["singleton_share"][ROI_NAMES[0]], percent=True),
        }
        for cls in class_ids:
            value = r["coverage"][CLASS_NAMES[cls]][ROI_NAMES[1]]
            row[f"{CLASS_NAMES[cls]} covered RoI 1 (%)"] = format_value(value, percent=True)
        rows.append(row)
    return "\n\n".join(
        [
            f"## Conformal prediction sets at α = {alpha:g} (definitions §18)",
            f"{sets}. λ̂ by conformal risk control on the held-out images bounds the expected "
            "loss of a new image by α (not the loss of each image); not reached: too few "
            "held-out images, every class is in the set.",
            markdown_table(rows, percent=[]),
        ]
    )


@dataclass
class ConformalOutputs(Result):
    """Every anchor rule's sets at risk level ``alpha``; ``sets``: what a set and the loss are;
    ``grid``: Λ; ``example``: the first reported image, its name and each rule's (H, W) set
    sizes."""

    alpha: float
    sets: str
    grid: torch.Tensor
    rules: list[RuleSets]
    example: tuple[torch.Tensor, str, list[torch.Tensor]] | None

    def write(self, results: EvalResults) -> Section:
        record = {r.name: r.summary() for r in self.rules}
        write_csv(results.output_dir / "conformal.csv", self._rows())
        names = [r.name for r in self.rules]
        risks = [r.control.risk for r in self.rules]
        lams = [r.control.lam for r in self.rules]
        jobs = [("conformal", job(risk_figures, self.grid, names, risks, lams, self.alpha,
                                  results.subject))]  # fmt: skip
        if self.example is not None:
            image, stem, sizes = self.example
            jobs.append(
                ("conformal", job(set_size_figures, image.permute(1, 2, 0), stem, names, sizes,
                                  results.subject))
            )  # fmt: skip
        curves = [
            (f"conformal/{name}/{key}", None, [0], [values[key]])
            for name, values in record.items()
            for key in ("lambda", "calibration_risk", "reported_loss")
        ]
        return Section(
            json={"conformal": {"alpha": self.alpha, "sets": self.sets, "rules": record}},
            table="\n\n" + conformal_table(record, self.alpha, self.sets, results.class_ids) + "\n",
            console=[self._console(record)],
            curves=curves,
            jobs=jobs,
        )

    def _rows(self) -> list[dict]:
        """``conformal.csv``: one row per rule × true class × RoI (0: the whole image)."""
        rows = []
        for r in self.rules:
            coverage, sizes = r.counts.coverage(), r.counts.mean_size(per_class=True)
            singletons = r.counts.singleton_share(per_class=True)
            for roi in range(len(ROI_NAMES)):
                for cls, name in enumerate(CLASS_NAMES):
                    rows.append({
                        "matrix": r.name, "lambda": r.control.lam, "class": name, "roi": roi,
                        "pixels": int(r.counts.pixels[roi, cls]),
                        "coverage": coverage[roi, cls].item(),
                        "mean_set_size": sizes[roi, cls].item(),
                        "singleton_share": singletons[roi, cls].item(),
                    })  # fmt: skip
        return rows

    def _console(self, record: dict) -> str:
        parts = [
            f"{name} λ̂ {r['lambda']:.3f}, loss {r['reported_loss']:.4f}, "
            f"set size {r['mean_set_size'][ROI_NAMES[0]]:.2f}"
            for name, r in record.items()
        ]
        line = f"conformal sets at α = {self.alpha:g}: " + "; ".join(parts)
        n = self.rules[0].control.n
        if not self.rules[0].control.reached:
            needed = math.ceil(1 / self.alpha - 1)
            line += (
                f"\n{n} held-out images cannot meet α = {self.alpha:g} (it takes at least "
                f"{needed}): every class is in every set; give --calibration_split or a larger α"
            )
        return line


def _per_class_and_roi(values: torch.Tensor) -> dict[str, dict[str, float]]:
    """(R + 1, N) values as class → RoI name → value."""
    return {
        name: {ROI_NAMES[r]: values[r, c].item() for r in range(len(ROI_NAMES))}
        for c, name in enumerate(CLASS_NAMES)
    }


def risk_figures(
    grid: np.ndarray,
    names: Sequence[str],
    risks: Sequence[np.ndarray],
    lams: Sequence[float],
    alpha: float,
    subject: str = "",
) -> Iterator[tuple[str, Figure]]:
    """``conformal_risk``: each rule's empirical risk on the held-out images against λ, α and
    each λ̂ marked (a drawing job)."""
    fig = Figure(figsize=(6, 4), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    for name, risk, lam in zip(names, risks, lams, strict=True):
        (line,) = ax.plot(grid, risk, label=f"{name} (λ̂ = {lam:.3f})")
        ax.axvline(lam, color=line.get_color(), linestyle=":", linewidth=1)
    ax.axhline(alpha, color="black", linestyle="--", linewidth=1, label=f"α = {alpha:g}")
    ax.set(xlabel="λ", ylabel="mean loss of the held-out images", xlim=(0, 1))
    title = "conformal risk control: risk against λ"
    ax.set_title(f"{title}\n{subject}" if subject else title, wrap=True)
    ax.grid(alpha=0.3)
    ax.legend()
    yield "conformal_risk", fig


def set_size_figures(
    image: np.ndarray,
    stem: str,
    names: Sequence[str],
    sizes: Sequence[np.ndarray],
    subject: str = "",
) -> Iterator[tuple[str, Figure]]:
    """``conformal_set_sizes``: the image and each rule's set size per pixel (a drawing job)."""
    panels = len(names) + 1
    fig = Figure(figsize=(3.2 * panels, 2.4), dpi=100, layout="constrained")
    axes = fig.subplots(1, panels, squeeze=False)[0]
    axes[0].imshow(image)
    axes[0].set_title(stem, fontsize=8)
    largest = max(1, *(int(s.max()) for s in sizes))
    for ax, name, size in zip(axes[1:], names, sizes, strict=True):
        shown = ax.imshow(size, cmap="viridis", vmin=1, vmax=largest, interpolation="nearest")
        ax.set_title(f"{name}: set size", fontsize=8)
    for ax in axes:
        ax.set_axis_off()
    fig.colorbar(shown, ax=list(axes[1:]), shrink=0.8, label="classes in the set")
    if subject:
        fig.suptitle(subject, fontsize=8)
    yield "conformal_set_sizes", fig
