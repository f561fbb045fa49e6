"""What the explorer page shows of an evaluation: its examples, the sweep's metrics, and the
named, target and certified points of the triangle (docs/definitions.md §11)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from costseg.classes import CLASS_NAMES
from costseg.costs import cost_or_symmetric, rescale
from costseg.metrics.names import PAPER_RATES, SEGMENT_RATES
from costseg.report.explorer import ExplorerExample, Marks, SweepData, embedded, write_explorer
from costseg.report.guarantee import Certificate
from costseg.report.results import EvalResults, GroupResult
from costseg.report.sections import Result, Section
from costseg.report.sweep import SweepPoint
from costseg.rules import Rule, vertex_matrices

ROIS = (0, 1, 2, 3, 4)


def named_points(
    rules: Sequence[Rule], vertices: torch.Tensor, scaling: str = "none"
) -> list[tuple[str, list[float]]]:
    """The named rules that are vertices of the triangle, with their weights (a rule with a
    defer row: where its class rows are; the page's defer slider sets the defer row).

    >>> from costseg.rules import parse_rules
    >>> V = vertex_matrices(["robotistic", "altruistic", "egoistic"])
    >>> named_points(parse_rules(["egoistic", "ml"]), V)
    [('egoistic', [0.0, 0.0, 1.0])]
    >>> named_points(parse_rules(["altruistic"], defer=0.5), V)
    [('altruistic', [0.0, 1.0, 0.0])]
    """
    points, n = [], vertices.shape[-1]
    for rule in rules:
        if rule.priors_alpha or rule.regional:  # no point of the triangle
            continue
        cost = cost_or_symmetric(rule.cost, n)[:n]
        cost = rescale(cost) if scaling == "mean" else cost
        for v in range(len(vertices)):
            if torch.equal(cost.to(vertices), vertices[v]):
                points.append((rule.name, [float(i == v) for i in range(len(vertices))]))
                break
    return points


def sweep_data(grid: GroupResult, class_ids: Sequence[int]) -> SweepData:
    """The grid's pixel metrics (RoI 0-4) and segment rates of the ``--classes``."""
    metrics: dict[str, dict[str, dict[str, list[float]]]] = {}
    for metric in PAPER_RATES:
        values = grid.pixels[metric]  # (K, R, N)
        metrics[metric] = {
            CLASS_NAMES[c]: {str(r): values[:, r, c].tolist() for r in ROIS} for c in class_ids
        }
    for metric in SEGMENT_RATES:
        if metric in grid.segments:
            values = grid.segments[metric]  # (K, C, R)
            metrics[metric] = {
                CLASS_NAMES[cls]: {str(r): values[:, c, r].tolist() for r in ROIS}
                for c, cls in enumerate(class_ids)
            }
    return SweepData(grid.group.weights.tolist(), metrics, grid.group.note)


def _marks(results: EvalResults, grid: GroupResult | None) -> Marks:
    marks, point = Marks(), results.find(SweepPoint)
    if grid is not None and point is not None:
        weights = grid.group.weights.tolist()
        marks.targets = [(point.target, weights[k]) for k in point.points(results, grid)]
    cert = results.find(Certificate)
    if cert is not None and cert.chosen is not None and cert.group.weights is not None:
        w = cert.group.weights[cert.chosen].tolist()
        marks.certified = [(f"certified ({cert.target})", w)]
    return marks


def _roi_at(roi: torch.Tensor | None, shape: tuple[int, int]) -> np.ndarray | None:
    """The RoI map at another label size (nearest location)."""
    if roi is None:
        return None
    rows = (np.arange(shape[0]) * roi.shape[0] // shape[0])[:, None]
    cols = (np.arange(shape[1]) * roi.shape[1] // shape[1])[None, :]
    return roi.numpy()[rows, cols]


def evaluation_examples(results: EvalResults) -> list[ExplorerExample]:
    """The evaluation's examples that kept their probabilities, as the page embeds them."""
    out = []
    for i, ex in enumerate(results.examples):
        if ex.probs is None:
            continue
        label = ex.label.numpy()
        out.append(
            embedded(
                ex.name or f"example_{i}",
                ex.image.permute(1, 2, 0).numpy(),
                ex.probs,
                label.astype(np.uint8),
                _roi_at(results.roi, label.shape),
                ex.uncertainty,
            )
        )
    return out


@dataclass
class ExplorerPage(Result):
    """``explorer.html`` of an evaluation (``evaluate.py --explorer``): the triangle of
    ``vertices`` (rescaled by ``vertex_scaling``) that the page mixes, and the defer cost of
    the named rules."""

    vertices: tuple[str, ...]
    vertex_scaling: str
    defer: float | None

    def write(self, results: EvalResults) -> Section:
        write_evaluation_explorer(results, self)
        return Section(console=[f"explorer: {results.output_dir / 'explorer.html'}"])


def write_evaluation_explorer(results: EvalResults, page: ExplorerPage) -> None:
    """Write ``explorer.html`` of an evaluation."""
    grid = next((g for g in results.groups if g.group.weights is not None), None)
    if grid is not None:
        vertices = grid.group.vertices
    else:
        vertices = vertex_matrices(list(page.vertices), page.vertex_scaling)
    named = named_points(results.named.group.rules, vertices, page.vertex_scaling)
    source = results.source
    notes = [
        f"source: {source.get('network') or source}",
        f"probabilities: {results.probabilities}; the examples' masks are decided on these "
        "probabilities rounded to float16",
    ]
    if "inference" in source:
        protocol = f"inference: {source['inference']}; test-time augmentation: {source['tta']}"
        notes.insert(1, protocol)
    if "uncertainty" in source:
        notes.append(f"uncertainty on hover: {source['uncertainty']}")
    write_explorer(
        results.output_dir / "explorer.html",
        evaluation_examples(results),
        vertices,
        list(page.vertices),
        named=named,
        sweep=None if grid is None else sweep_data(grid, results.class_ids),
        marks=_marks(results, grid),
        notes=notes,
        defer=page.defer,
    )
