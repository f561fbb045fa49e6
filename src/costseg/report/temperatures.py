"""The outputs of ``--temperature_sweep`` (docs/definitions.md §6): every named rule decided on
``softmax(z / T)`` for each T of the sweep (and the fitted T), one rule group per T.

``temperature_sweep.csv`` / ``.json`` hold every rule's rows at every T, ``figures/temperature_*``
each class's rates in RoI 1 against T, TensorBoard the same curves (step: 100 · T).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.metrics.names import DEFER_RATES, PIXEL_RATES
from costseg.report.curves import Curves, curve_figures
from costseg.report.drawing import job
from costseg.report.files import write_csv, write_json
from costseg.report.results import EvalResults, GroupResult
from costseg.report.sections import Curve, Section
from costseg.report.sweep import SWEEP_ROIS


def temperature_outputs(results: EvalResults, mine: list[GroupResult]) -> Section:
    """The files, figures and TensorBoard curves of the groups of the temperature sweep."""
    groups = sorted(mine, key=lambda g: g.group.temperature)
    rows = [row for g in groups for row in g.rows(results.class_ids, SWEEP_ROIS)]
    write_csv(results.output_dir / "temperature_sweep.csv", rows)
    write_json(results.output_dir / "temperature_sweep.json", {"rows": rows})
    curves = _curves(groups, results.class_ids)
    return Section(
        jobs=[("calibration", job(curve_figures, curves, results.subject))],
        curves=list(_tensorboard_curves(groups, results.class_ids)),
    )


def _curves(groups: list[GroupResult], class_ids: Sequence[int]) -> list[Curves]:
    """Per class, each rule's pixel rates in RoI 1 against T."""
    temps = [g.group.temperature for g in groups]
    curves = []
    for cls in class_ids:
        name = CLASS_NAMES[cls]
        series = {
            f"{rule} {metric}": [g.pixels[metric][k, 1, cls].item() for g in groups]
            for k, rule in enumerate(c["matrix"] for c in groups[0].group.columns)
            for metric in PIXEL_RATES
        }
        title = f"{name} in RoI 1 ({ROI_NAMES[1]})"
        curves.append(
            (f"temperature_{name}", temps, series, "temperature T of softmax(z / T)", title)
        )
    return curves


def _tensorboard_curves(groups: list[GroupResult], class_ids: Sequence[int]) -> Iterator[Curve]:
    """Each rule's pixel rates (and deferral) in RoI 1 along T (step: 100 · T)."""
    steps = [round(100 * g.group.temperature) for g in groups]
    defers = groups[0].group.defers
    for k, rule in enumerate(groups[0].group.names):
        for cls in class_ids:
            for metric in (*PIXEL_RATES, *(DEFER_RATES if defers else ())):
                values = [g.pixels[metric][k, 1, cls].item() for g in groups]
                yield f"temperature_sweep/{rule}/{metric}_roi1", CLASS_NAMES[cls], steps, values
        if defers:
            values = [g.pixels["deferred_rate"][k, 0].item() for g in groups]
            yield f"temperature_sweep/{rule}/deferred_rate", None, steps, values
