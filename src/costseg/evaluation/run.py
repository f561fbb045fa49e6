"""The ``evaluate.py`` job: plan (once) → one loop over the images → results → reports.

:func:`run` fits and certifies on the calibration images of the plan
(:mod:`costseg.evaluation.plan`, :mod:`costseg.evaluation.held_out`), then passes over the
reported images once: scores → probabilities → every rule group → metrics
(:mod:`costseg.metrics.scoring`, shared with validation). :func:`evaluate` plans, runs and hands
the results to :mod:`costseg.report.evaluation`; the output folder is marked ``INCOMPLETE``
until every file is written. Under ``torchrun`` the metrics' sums of all processes are merged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict

import torch
import torch.distributed as dist
from torch.utils.data import Dataset

from costseg import workers
from costseg.calibration.scaling import Scaling
from costseg.classes import CLASS_NAMES, NUM_ROIS
from costseg.evaluation.anomalies import AnomalyPass
from costseg.evaluation.held_out import certify, fit_scaling
from costseg.evaluation.plan import EvalPlan, plan, rank
from costseg.meta.collect import SegmentCollector, SegmentResults
from costseg.meta.fusion import FusedRules
from costseg.meta.models import MetaModels, fit_models
from costseg.meta.models import scores as meta_scores
from costseg.metrics import CalibrationError
from costseg.metrics.scoring import GroupMetrics, score_batch
from costseg.networks.probs_files import save_data_record
from costseg.networks.sources import Batch, Source, batches
from costseg.networks.uncertainty import output_maps
from costseg.options import EvalOptions
from costseg.progress import progress
from costseg.report.outputs import INCOMPLETE, BatchWriter, mark_complete
from costseg.report.results import EvalResults, Example, GroupResult
from costseg.rules import (
    Rule,
    RuleGroup,
    apply_rules,
    masked_groups,
    named_group,
    temperature_group,
)


def run(plan: EvalPlan, after_batch: Callable[[list[Example]], None] | None = None) -> EvalResults:
    """Calibrate and certify on the held-out images, then one pass over the reported ones;
    ``after_batch(examples)`` after each of its batches (e.g. to start drawing figures)."""
    opts, extra = plan.options, {}
    scaling = Scaling()
    if opts.calibrate:
        scaling = fit_scaling(
            _calibration_batches(plan, "fit scaling"), opts.calibrate, plan.source
        )
        print(f"calibration: {scaling.describe()}")
        extra["scaling"] = scaling.to_dict()
        if opts.temperature_sweep and scaling.kind == "temperature":
            named = named_group(plan.groups)
            plan.groups.append(temperature_group(named.rules, scaling.temperature))
    if plan.meta_images is not None:
        extra["meta_models"] = _fit_meta(plan, scaling)
    if opts.guarantee is not None:
        group = next(g for g in plan.groups if g.candidates)
        extra["certificate"] = certify(
            _calibration_batches(plan, "certify"),
            group,
            lambda b: _probabilities(plan, b, scaling),
            plan.priors.at,
            opts.target,
            opts.maximize,
            opts.guarantee,
            opts.guarantee_method,
            plan.class_ids,
        )
    return _report_pass(plan, scaling, extra, after_batch)


def _meta_rules(plan: EvalPlan) -> list[Rule]:
    """The rules whose segments the meta models judge: the named ones (``--meta``) and the
    fused ones (``--fuse``)."""
    rules = list(named_group(plan.groups).rules) if plan.options.meta else []
    fusion = _fusion(plan)
    if fusion is not None:
        rules += [r for r in fusion.decide.fused if r.name not in {q.name for q in rules}]
    return rules


def _fusion(plan: EvalPlan) -> RuleGroup | None:
    return next((g for g in plan.groups if isinstance(g.decide, FusedRules)), None)


def _fit_meta(plan: EvalPlan, scaling: Scaling) -> dict[str, MetaModels]:
    """Fit the meta models of every rule of :func:`_meta_rules` on the segments of the held-out
    images; hand the fused rules theirs (without MI: a rule decides from the probabilities)."""
    rules = _meta_rules(plan)
    collector = SegmentCollector(rules)
    dataset, indices = plan.meta_images
    desc = f"meta features ({len(indices)} held-out images)" if plan.options.progress else None
    with torch.inference_mode():
        for batch in batches(
            plan.source, dataset, indices, plan.batch_size, plan.device, plan.num_workers, desc
        ):
            probs = _probabilities(plan, batch, scaling)
            priors, _ = plan.priors.at(tuple(batch.labels.shape[-2:]))
            preds = apply_rules(probs, rules, priors)
            collector.add(probs, preds, batch.labels, priors, batch.expected_entropy, batch.stems)
    fitting = "meta models, rule by rule" if plan.options.progress else None
    models = {
        r.name: fit_models(collector.table(r.name), collector.features(r.name), len(indices))
        for r in progress(rules, fitting)
    }
    fusion = _fusion(plan)
    if fusion is not None:
        own = {}
        for r in fusion.decide.fused:
            features = [f for f in collector.features(r.name) if not f.startswith("MI")]
            same = features == models[r.name].features
            own[r.name] = (
                models[r.name]
                if same
                else fit_models(collector.table(r.name), features, len(indices))
            )
        fusion.decide.use(own)
    fitted = {r: m.num_segments for r, m in models.items()}
    print(f"meta models fitted on {len(indices)} held-out images: segments {fitted}")
    return models


def _report_pass(plan: EvalPlan, scaling: Scaling, extra: dict, after_batch) -> EvalResults:
    opts, device = plan.options, plan.device
    classes, extra["instances"] = plan.instance_classes
    print(extra["instances"])
    metrics = [
        GroupMetrics(
            g,
            len(CLASS_NAMES),
            NUM_ROIS,
            None if g.temperature else plan.class_ids,
            plan.canvas,
            instance_classes=classes,
        ).to(device)
        for g in plan.groups
    ]
    ece = {"raw": CalibrationError(len(CLASS_NAMES)).to(device)}
    if scaling.kind != "none":
        ece["scaled"] = CalibrationError(len(CLASS_NAMES)).to(device)
    named = plan.groups.index(named_group(plan.groups))
    masked = [plan.groups.index(g) for g in masked_groups(plan.groups)]
    writer = BatchWriter(plan.output_dir, plan.groups[named].names, opts.save_predictions)
    if opts.save_probs and plan.data is not None and rank() == 0:  # --probs: no --data_root
        save_data_record(plan.output_dir / "probs", plan.data, plan.priors.priors)
    examples: list[Example] = []
    desc = "evaluate" if opts.progress and rank() == 0 else None
    described = opts.meta or opts.save_segments
    collector = SegmentCollector(plan.groups[named].rules, opts.num_examples) if described else None
    unknown = None
    if opts.anomalies:
        unknown = AnomalyPass(plan.groups[named].rules, len(CLASS_NAMES), opts.num_examples)
    with torch.inference_mode():
        # images with uncertainty maps (the segments' and the anomaly scores' MI: every image)
        every = opts.save_probs or described or opts.anomalies
        mapped = None if every else opts.num_examples
        source, workers = plan.source, plan.num_workers
        for batch in batches(
            source, plan.dataset, plan.indices, plan.batch_size, device, workers, desc, mapped
        ):
            probs = _probabilities(plan, batch, scaling)
            uncertainty = None
            if opts.save_probs or len(examples) < opts.num_examples:
                uncertainty = _uncertainty(plan, batch, probs, scaling)
            if opts.save_probs:  # evaluate exactly what is saved, so --probs reproduces it
                probs = probs.half().float()
                writer.save_probs(batch.stems, probs, uncertainty)
            _update_ece(ece, plan, batch, probs)
            priors, roi = plan.priors.at(tuple(batch.labels.shape[-2:]))
            ids = batch.instances
            by_temperature = _tempered(plan, batch, probs)
            preds = [
                score_batch(g, m, by_temperature[g.temperature], batch.labels, priors, roi, ids)
                for g, m in zip(plan.groups, metrics, strict=True)
            ]
            writer.save_predictions(batch.stems, preds[named])
            if collector is not None:
                entropy = batch.expected_entropy
                collector.add(probs, preds[named], batch.labels, priors, entropy, batch.stems)
            if unknown is not None:
                entropy = batch.expected_entropy
                unknown.update(batch.images, probs, batch.anomalies, preds[named], priors, entropy)
            kept = opts.explorer and probs
            shown = torch.cat([preds[g] for g in masked], 1)
            _keep_examples(examples, opts.num_examples, batch, shown, kept, uncertainty)
            if after_batch:
                after_batch(examples)
    extra["ece"] = {k: m.compute() for k, m in ece.items()}
    if unknown is not None:
        extra["anomalies"] = unknown.result() | {"examples": unknown.examples}
    segments = None
    if collector is not None:
        models = extra.pop("meta_models", None) if opts.meta else None
        tables = {r.name: collector.table(r.name) for r in collector.rules}
        segments = SegmentResults(tables, collector.images, collector.maps, models)
        if models is not None:
            segments.scores = {r: meta_scores(models[r], tables[r]) for r in tables if tables[r]}
            segments.fitted_on = {
                "images": len(plan.meta_images[1]),
                "segments": {r: m.num_segments for r, m in models.items()},
            }
    extra.pop("meta_models", None)
    return EvalResults(
        output_dir=plan.output_dir,
        options=asdict(opts),
        source=plan.source.description,
        probabilities=_describe_probabilities(plan, scaling),
        class_ids=plan.class_ids,
        groups=[GroupResult(g, **m.compute()) for g, m in zip(plan.groups, metrics, strict=True)],
        examples=examples,
        roi=plan.priors.roi_map(),
        num_images=plan.num_reported,
        extra=extra,
        segments=segments,
    )


def evaluate(
    opts: EvalOptions, source: Source | None = None, dataset: Dataset | None = None
) -> EvalResults | list[EvalResults]:
    """Plan, run, and (on rank 0) write every output; returns the results (a list of them, one
    per shift, with several ``--shift``: :mod:`costseg.evaluation.shifts`). ``source`` and
    ``dataset`` replace the ones the options name (:func:`costseg.api.evaluate`).

    Figures known before the loop ends are drawn meanwhile, by workers of the forkserver
    (:mod:`costseg.workers`), which starts first, while the network loads. The output
    folder is marked ``INCOMPLETE`` until every file is written; an interrupt or a failed write
    says where the partial outputs are."""
    workers.start()
    planned = plan(opts, source, dataset)
    if len(planned.shifts) > 1:
        from costseg.evaluation.shifts import evaluate_shifts

        return evaluate_shifts(planned, evaluate_plan)
    return evaluate_plan(planned)


def evaluate_plan(planned: EvalPlan) -> EvalResults:
    """Run ``planned`` and write its outputs into its output folder (see :func:`evaluate`)."""
    opts, early = planned.options, None
    out = planned.output_dir
    try:
        if rank() == 0:
            from costseg.report.early_figures import EarlyFigures
            from costseg.report.results import figure_subject

            roi = planned.priors.roi_map()
            subject = figure_subject(planned.source.description, opts.shift or [])
            early = EarlyFigures(out, planned.groups, roi, opts.num_examples, subject)
        results = run(planned, early.after_batch if early else None)
        if early:
            from costseg.report.evaluation import write_evaluation

            write_evaluation(results, early)
    except (KeyboardInterrupt, ValueError, OSError, workers.Stalled, dist.DistError) as err:
        if early:
            early.cancel()
        partial = f"the partial outputs in {out} are marked {INCOMPLETE}"
        if isinstance(err, KeyboardInterrupt):
            raise KeyboardInterrupt(partial) from None
        if isinstance(err, dist.DistError):  # a peer process that stopped answering
            first = str(err).strip().splitlines()[0]
            raise workers.Stalled(f"another evaluation process: {first}; {partial}") from err
        if isinstance(err, workers.Stalled):
            raise workers.Stalled(f"{err}; {partial}") from err
        if isinstance(err, ValueError):  # bad data met on the way (an unreadable file)
            raise ValueError(f"{str(err).strip()}; {partial}") from err
        # a full disk under TensorBoard's writer thread names no file: the folder it writes in
        raise OSError(f"{err.strerror or err}: {err.filename or out}; {partial}") from err
    except BaseException:
        if early:
            early.cancel()
        raise
    if rank() == 0:
        mark_complete(out)
    return results


def _calibration_batches(plan: EvalPlan, what: str):
    dataset, indices = plan.calibration
    desc = f"{what} ({len(indices)} calibration images)" if plan.options.progress else None
    with torch.inference_mode():
        yield from batches(
            plan.source, dataset, indices, plan.batch_size, plan.device, plan.num_workers, desc, 0
        )


def _probabilities(plan: EvalPlan, batch: Batch, scaling: Scaling) -> torch.Tensor:
    if scaling.kind != "none":
        return scaling.apply(plan.source.logits_of(batch.scores))
    return plan.source.probabilities_of(batch.scores)


def _tempered(plan: EvalPlan, batch: Batch, probs: torch.Tensor) -> dict:
    """The probabilities of every temperature a group asks for (None: the main ones)."""
    out = {None: probs}
    for t in {g.temperature for g in plan.groups if g.temperature}:
        out[t] = Scaling("temperature", temperature=t).apply(plan.source.logits_of(batch.scores))
    return out


def _update_ece(ece: dict, plan: EvalPlan, batch: Batch, probs: torch.Tensor) -> None:
    if "scaled" in ece:
        ece["scaled"].update(probs, batch.labels)
        probs = _probabilities(plan, batch, Scaling())
    ece["raw"].update(probs, batch.labels)


def _describe_probabilities(plan: EvalPlan, scaling: Scaling) -> str:
    base = plan.source.probabilities  # saved ones, Monte-Carlo dropout, or None: the softmax
    if scaling.kind == "none" and base:
        text = f"{base}, no scaling"
    else:
        text = (f"{base}; " if base else "") + scaling.describe()
    text += "; rounded to float16 as saved" if plan.options.save_probs else ""
    if len(plan.shifts) == 1:
        text += f"; the images seen through {plan.shifts[0]} (definitions §17)"
    return text


def _uncertainty(
    plan: EvalPlan, batch: Batch, probs: torch.Tensor, scaling: Scaling
) -> dict[str, torch.Tensor]:
    """The uncertainty maps (B, H, W) of the source's probabilities before any scaling (``probs``
    themselves when there is none)."""
    if scaling.kind != "none":
        probs = _probabilities(plan, batch, Scaling())
    return output_maps(probs, batch.expected_entropy)


def _keep_examples(
    examples: list, limit: int, batch: Batch, preds: torch.Tensor, probs, uncertainty
) -> None:
    """The first ``limit`` images with their float16 uncertainty maps; with ``probs`` (the
    explorer's), their float16 probabilities."""
    for i in range(min(len(batch.images), limit - len(examples))):
        kept = None if probs is False else probs[i].to("cpu", torch.float16)
        image, label = batch.images[i].cpu(), batch.labels[i].cpu()
        maps = {k: v[i].to("cpu", torch.float16) for k, v in uncertainty.items()}
        examples.append(Example(image, label, preds[i].cpu(), batch.stems[i], kept, maps))
