"""Outputs about the probabilities: scaling, ECE and reliability diagrams, the temperature
sweep, and the value system chosen with a guarantee.

``calibration.json`` and ``calibration.csv`` (scaling; ECE, class-wise ECE, NLL and Brier score
before / after), ``figures/reliability.png``,
``temperature_sweep.csv|json`` and ``figures/temperature_*.png``, ``guarantee.json`` and
``guarantee_cost.yaml``.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from costseg.classes import CLASS_NAMES, ROI_NAMES
from costseg.costs import save_cost
from costseg.metrics.names import PIXEL_RATES
from costseg.report.curves import Curves, calibration_figures
from costseg.report.drawing import Job, job
from costseg.report.files import write_csv, write_json
from costseg.report.results import EvalResults
from costseg.report.sweep import SWEEP_ROIS
from costseg.rules import RuleGroup

SCORES = ("ece", "classwise_ece", "nll", "brier")  # docs/definitions.md §6, §13


def calibration_rows(ece: Mapping[str, Mapping[str, torch.Tensor]]) -> list[dict]:
    """One row per set of probabilities (raw, scaled): its :data:`SCORES` and the ECE of the
    pixels predicted as each class (``ece_<class>``; NaN for a class never predicted)."""
    return [
        {"probabilities": name}
        | {score: float(out[score]) for score in SCORES}
        | {f"ece_{c}": float(v) for c, v in zip(CLASS_NAMES, out["per_class"], strict=False)}
        for name, out in ece.items()
    ]


def calibration_record(rows: list[dict]) -> dict:
    """``{score: {probabilities: value}}`` of :func:`calibration_rows`, and "ece_per_class"
    ``{probabilities: {class: value}}``, for results.json and calibration.json."""
    record = {score: {r["probabilities"]: r[score] for r in rows} for score in SCORES}
    record["ece_per_class"] = {
        r["probabilities"]: {c: r[f"ece_{c}"] for c in CLASS_NAMES if f"ece_{c}" in r} for r in rows
    }
    return record


def calibration_line(rows: list[dict]) -> str:
    """``calibration (15 bins): raw ECE 0.1234, class-wise ECE …, NLL …, Brier …; scaled …``."""
    return "calibration (15 bins): " + "; ".join(
        f"{r['probabilities']} ECE {r['ece']:.4f}, class-wise ECE {r['classwise_ece']:.4f}, "
        f"NLL {r['nll']:.4f}, Brier {r['brier']:.4f}"
        for r in rows
    )


def write_calibration(results: EvalResults) -> list[tuple[str, Job]]:
    """Calibration figures, reliability diagrams, temperature sweep and guarantee, as far as
    evaluated; returns the figures, undrawn, as ``(TensorBoard prefix, job)``
    (:mod:`costseg.report.drawing`)."""
    out, extra = results.output_dir, results.extra
    ece = extra.get("ece", {})
    rows = calibration_rows(ece)
    record = {"probabilities": results.probabilities, "scaling": extra.get("scaling")}
    write_json(out / "calibration.json", record | calibration_record(rows))
    if rows:
        write_csv(out / "calibration.csv", rows)
        print(calibration_line(rows))
    if "certificate" in extra:
        _write_certificate(results)
    return [
        ("calibration", job(calibration_figures, ece, _temperature_sweep(results), results.subject))
    ]


def _temperature_sweep(results: EvalResults) -> list[Curves]:
    """``temperature_sweep.csv|json``; returns the curves of its figures."""
    groups = sorted(
        (g for g in results.groups if g.group.temperature), key=lambda g: g.group.temperature
    )
    if not groups:
        return []
    rows = [row for g in groups for row in g.rows(results.class_ids, SWEEP_ROIS)]
    write_csv(results.output_dir / "temperature_sweep.csv", rows)
    write_json(results.output_dir / "temperature_sweep.json", {"rows": rows})
    temps = [g.group.temperature for g in groups]
    curves = []
    for cls in results.class_ids:
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


def _write_certificate(results: EvalResults) -> None:
    cert, out = results.extra["certificate"], results.output_dir
    ltt, group = cert.ltt, cert.group
    record = {
        "target": cert.target,
        "maximize": cert.maximize,
        "alpha": ltt.alpha,
        "delta": ltt.delta,
        "method": ltt.method,
        "bound": ltt.bound,
        "calibration_images": cert.num_images,
        "candidates": len(group.names),
        "certified": [group.columns[i] for i in ltt.valid.tolist()],
        "found": cert.chosen is not None,
    }
    if cert.chosen is None:
        print(
            f"no value system is certified for {cert.target} at δ = {ltt.delta} "
            f"with {cert.num_images} calibration images"
        )
        write_json(out / "guarantee.json", record)
        return
    k = cert.chosen
    record |= {
        "chosen": group.columns[k],
        "calibration_risk": float(ltt.risk[k]),
        "pvalue": float(ltt.pvalues[k]),
        "images_used": int(ltt.n[k]),
        "images_left_out": int(ltt.n_undefined[k]),
        "calibration_value": float(cert.objective[k]),
        "report": _reported(results, group, k),
    }
    matrix = group.cost(k)
    if matrix is not None:
        save_cost(out / "guarantee_cost.yaml", matrix, "guaranteed")
        record["matrix"] = matrix.tolist()
    write_json(out / "guarantee.json", record)
    print(
        f"certified for {cert.target} with P(risk > {ltt.alpha:.3g}) <= {ltt.delta}: "
        f"{group.names[k]} (calibration risk {ltt.risk[k]:.4f} on {ltt.n[k]} images, "
        f"{ltt.n_undefined[k]} left out; {cert.maximize} {float(cert.objective[k]):.4f}); "
        f"{len(ltt.valid)} of {len(group.names)} candidates certified"
    )


def _reported(results: EvalResults, group: RuleGroup, k: int) -> dict:
    """The chosen rule's precision and recall on the reported images (RoI 0-2, --classes)."""
    pixels = results.result_of(group).pixels
    return {
        f"{CLASS_NAMES[cls]}/roi{roi}": {m: pixels[m][k, roi, cls].item() for m in PIXEL_RATES}
        for cls in results.class_ids
        for roi in SWEEP_ROIS
    }
